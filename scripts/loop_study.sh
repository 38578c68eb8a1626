#!/usr/bin/env bash
# A whole MLMC study the cluster way with plain bash, no batch system: plan,
# compute shards, merge, repeat until nothing is missing; then `roughuq mlmc`
# writes the estimate from the stored samples.
#
#   scripts/loop_study.sh [OPTIONS] CONFIG TOL [STUDY] [CHUNK]
#
#   CONFIG  study config (YAML)          TOL    as for `roughuq mlmc --tol`
#   STUDY   study file (results.h5)      CHUNK  samples per shard (20)
#
# Options; each has an environment variable (in brackets), an option wins:
#   --jobs N      shards computed at once, one core each [RUQ_JOBS]; default 1,
#                 one shard at a time on all cores (roughuq's default --workers)
#   --workers N   worker processes per shard [RUQ_WORKERS]; default: roughuq's
#                 (all cores), 1 with --jobs N > 1
#   --retries N   rounds in a row with failed shards before stopping [RUQ_RETRIES] (3)
#   ROUGHUQ       the roughuq command (default `roughuq`), e.g. "python -m rough_uq.cli"
#
# A shard that fails (killed, out of memory) is reported and its samples are
# planned again in the next round. Stopped at any point, the same command
# continues: shards already written are merged first.
set -euo pipefail

jobs="${RUQ_JOBS:-1}"; workers="${RUQ_WORKERS:-}"; retries="${RUQ_RETRIES:-3}"
read -r -a ruq <<< "${ROUGHUQ:-roughuq}"
die() { echo "loop_study.sh: $*" >&2; exit 1; }
positional=()
while [ $# -gt 0 ]; do
    case "$1" in
        --jobs) jobs="$2"; shift 2 ;;
        --workers) workers="$2"; shift 2 ;;
        --retries) retries="$2"; shift 2 ;;
        -h|--help) sed -n '2,/^set -euo/p' "${BASH_SOURCE[0]}" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
        --) shift; positional+=("$@"); break ;;
        -*) die "unknown option $1 (see --help)" ;;
        *) positional+=("$1"); shift ;;
    esac
done
[ ${#positional[@]} -ge 2 ] && [ ${#positional[@]} -le 4 ] \
    || die "usage: loop_study.sh [OPTIONS] CONFIG TOL [STUDY] [CHUNK]"
config="${positional[0]}"; tol="${positional[1]}"; study="${positional[2]:-results.h5}"; chunk="${positional[3]:-20}"
shards="${study%.h5}.shards"
mkdir -p "$shards"
shopt -s nullglob

merge() {   # every complete shard into the study (a killed shard leaves only a .partial-* file)
    local files=("$shards"/shard-*.h5)
    if [ ${#files[@]} -gt 0 ]; then
        "${ruq[@]}" merge "${files[@]}" --into "$study"
        rm -f "${files[@]}"
    fi
    rm -f "$shards"/shard-*.partial-*
}
[ -n "$workers" ] || [ "$jobs" -eq 1 ] || workers=1
worker_opts=()
[ -z "$workers" ] || worker_opts=(--workers "$workers")
shard() {   # stage level indices: one shard, its failure reported but not fatal
    "${ruq[@]}" sample --study "$study" --stage "$1" --level "$2" --indices "$3" \
        --out "$shards/shard-$1-$2-${3%%:*}.h5" "${worker_opts[@]}" --quiet ||
        echo "loop_study.sh: shard $3 of level $2 failed (status $?); planned again next round" >&2
}

# A screening that was stopped is continued by the same command.
"${ruq[@]}" screen "$config" --out "$study" --quiet
merge

failed=0
while true; do
    # One line per shard: "STAGE LEVEL A:B".
    work=$("${ruq[@]}" mlmc --study "$study" --tol "$tol" --plan --shards "$chunk")
    [ -n "$work" ] || break
    n=0
    while read -r stage level indices; do
        if [ "$jobs" -gt 1 ]; then
            while [ "$(jobs -rp | wc -l)" -ge "$jobs" ]; do wait -n || true; done
            shard "$stage" "$level" "$indices" &
        else
            shard "$stage" "$level" "$indices"
        fi
        n=$((n + 1))
    done <<< "$work"
    wait
    files=("$shards"/shard-*.h5)
    if [ ${#files[@]} -lt "$n" ]; then
        failed=$((failed + 1))
        [ "$failed" -lt "$retries" ] \
            || die "$retries rounds in a row had failed shards; fix and run the same command again"
    else
        failed=0
    fi
    merge
done
"${ruq[@]}" mlmc --study "$study" --tol "$tol" --quiet || [ $? -eq 3 ]  # 3: tolerance not met, result stored
