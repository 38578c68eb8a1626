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

round=0
while true; do
    # One line per shard: "STAGE LEVEL A:B".
    work=$(roughuq mlmc --study "$study" --tol "$tol" --plan --shards "$chunk")
    [ -n "$work" ] || break
    round=$((round + 1))
    while read -r stage level indices; do
        roughuq sample --study "$study" --stage "$stage" --level "$level" --indices "$indices" \
            --out "$shards/r$round-s$stage-l$level-${indices%%:*}.h5" --quiet
    done <<< "$work"
    roughuq merge "$shards"/r$round-*.h5 --into "$study"
done
roughuq mlmc --study "$study" --tol "$tol" || [ $? -eq 3 ]  # 3: tolerance not met, result stored
