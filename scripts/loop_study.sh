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
# A shard that fails (killed, out of memory) is reported (with --jobs, counted
# per round) and its samples are planned again in the next round. Ctrl-C, or
# SIGTERM to the script alone, stops the loop and the commands it runs (status
# 130 / 143; a stopped shard writes nothing). Stopped at any point, the same
# command continues: shards already written are merged first. Exit status: 0
# the tolerance met, 3 the estimate is stored but did not meet it (as
# `roughuq mlmc`), 130 / 143 stopped, 1 or 2 an error.
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
shard_command() {   # stage level indices: the command of one shard, in the array `shard_cmd`
    shard_cmd=("${ruq[@]}" sample --study "$study" --stage "$1" --level "$2" --indices "$3"
             --out "$shards/shard-$1-$2-${3%%:*}.h5" "${worker_opts[@]}" --quiet)
}

# Every long command (the screening, each shard, the run) runs in the background, --jobs 1 too, and the loop
# waits for it: a trapped signal interrupts `wait` (not a command in the foreground), and a script's
# background commands ignore Ctrl-C, so that they stop when this script stops them, with SIGTERM.
stoppable() {   # command...: run it so that stop() can stop it; its status
    "$@" &
    wait $!
}
stop() {   # status: stop the commands still running (screening, shards, run), then exit
    trap - INT TERM
    local running
    running=$(jobs -pr)
    [ -z "$running" ] || kill -TERM $running 2> /dev/null || true
    wait || true
    echo "loop_study.sh: stopped; run the same command to continue" >&2
    exit "$1"
}
trap 'stop 130' INT
trap 'stop 143' TERM

# A screening that was stopped is continued by the same command.
stoppable "${ruq[@]}" screen "$config" --out "$study" --quiet
merge

failed=0
while true; do
    # One line per shard: "STAGE LEVEL A:B".
    work=$("${ruq[@]}" mlmc --study "$study" --tol "$tol" --plan --shards "$chunk")
    [ -n "$work" ] || break
    n=0
    while read -r stage level indices; do
        shard_command "$stage" "$level" "$indices"
        if [ "$jobs" -eq 1 ]; then
            status=0
            stoppable "${shard_cmd[@]}" || status=$?
            [ "$status" -eq 0 ] || echo "loop_study.sh: shard $indices of level $level failed (status $status)" >&2
        else
            while [ "$(jobs -rp | wc -l)" -ge "$jobs" ]; do wait -n || true; done
            # The command itself in the background (no function, no subshell): its pid is the shard's, for stop.
            "${shard_cmd[@]}" &
        fi
        n=$((n + 1))
    done <<< "$work"
    wait || true
    files=("$shards"/shard-*.h5)
    if [ ${#files[@]} -lt "$n" ]; then
        echo "loop_study.sh: $((n - ${#files[@]})) of $n shards failed; planned again next round" >&2
        failed=$((failed + 1))
        [ "$failed" -lt "$retries" ] \
            || die "$retries rounds in a row had failed shards; fix and run the same command again"
    else
        failed=0
    fi
    merge
done
# Status as roughuq mlmc's: 0 the tolerance met, 3 not met (the result is stored and says what to change).
stoppable "${ruq[@]}" mlmc --study "$study" --tol "$tol" --quiet
