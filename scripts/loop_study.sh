#!/usr/bin/env bash
# A whole MLMC run done the cluster way, with a plain bash loop: plan, compute
# shards (each `roughuq sample` could be a separate job), merge, repeat until
# nothing is missing; then `roughuq mlmc` finishes from the stored samples.
#
#   scripts/loop_study.sh CONFIG TOL [STUDY] [CHUNK]
#
# CHUNK is the number of samples per shard (default 20).
set -euo pipefail
config="$1"; tol="$2"; study="${3:-results.h5}"; chunk="${4:-20}"
shards="${study%.h5}.shards"
mkdir -p "$shards"

[ -f "$study" ] || roughuq screen "$config" --out "$study"

# Print "stage level start stop" lines, one per shard, from the JSON plan.
plan_shards() {
    roughuq mlmc --study "$study" --tol "$tol" --plan --json | python3 -c '
import json, sys
plan, chunk = json.load(sys.stdin), int(sys.argv[1])
for row in plan["levels"]:
    for part in row["indices"]:
        start, stop = map(int, part.split(":"))
        for a in range(start, stop, chunk):
            print(plan["stage"], row["level"], a, min(a + chunk, stop))
' "$chunk"
}

round=0
while true; do
    work=$(plan_shards)
    [ -n "$work" ] || break
    round=$((round + 1))
    while read -r stage level start stop; do
        roughuq sample --study "$study" --stage "$stage" --level "$level" --indices "$start:$stop" \
            --out "$shards/r$round-s$stage-l$level-$start.h5" --quiet
    done <<< "$work"
    roughuq merge "$shards"/r$round-*.h5 --into "$study"
done
roughuq mlmc --study "$study" --tol "$tol"
