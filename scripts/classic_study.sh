#!/usr/bin/env bash
# The classic studies of SPEC section 6 at the paper's tolerances, reproduced with roughuq commands.
#
#   scripts/classic_study.sh [WORKDIR]
#
# Contact area (L = 2, grids 256..4096, perimeter-corrected area in percent):
# screening, then MLMC and plain MC at eps = 1.0, 0.9, ..., 0.2 and 0.1.
# Cluster density (L = 3, grids 96..3072, mean of the 4- and 8-connected
# counts, per unit area): screening, then MLMC and MC at eps = 40, 30, 20, 15,
# 10, 8, 6, 4, 3, 2. Each table is timed (wall seconds, including the
# screening and every command's start-up) and printed by
# scripts/classic_tables.py against the references of docs/classic/ (computed
# by scripts/classic_hierarchy.py on grids finer than any level used).
# Every command resumes where it stopped if the script is interrupted and run
# again. About 18 minutes on 2 cores (README, "The classic study").
# The tolerance lists are environment variables (AREA_TOLS, AREA_EXTRA_TOLS,
# CLUSTER_TOLS; set to an empty string, a table is skipped, e.g. AREA_TOLS=""
# AREA_EXTRA_TOLS="" for the cluster table alone); WORKERS sets the worker
# processes (default 2).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
reference="$here/../docs/classic/reference.json"
work="${1:-classic}"
mkdir -p "$work"
cd "$work"

AREA_TOLS=${AREA_TOLS-"1.0 0.9 0.8 0.7 0.6 0.5 0.4 0.3 0.2"}
AREA_EXTRA_TOLS=${AREA_EXTRA_TOLS-"0.1"}
CLUSTER_TOLS=${CLUSTER_TOLS-"40 30 20 15 10 8 6 4 3 2"}
WORKERS=${WORKERS:-2}

# run METHOD STUDY TOL: an estimation run; exit status 3 (tolerance not met, result stored) is reported, not fatal.
run() {
    roughuq "$1" --study "$2" --tol "$3" --workers "$WORKERS" > "$1_$3.log" 2>&1 || {
        status=$?
        [ "$status" -eq 3 ] || { cat "$1_$3.log"; exit "$status"; }
    }
    tail -n 4 "$1_$3.log"
}

# table NAME STUDY CONFIG TOLS...: screening and both methods at every tolerance, timed.
table() {
    local name=$1 study=$2 config=$3
    shift 3
    local start=$SECONDS
    roughuq screen "$config" --out "$study" --workers "$WORKERS" > "screen_$name.log" 2>&1
    for tol in "$@"; do
        run mlmc "$study" "$tol"
        run mc "$study" "$tol"
    done
    echo "$name: $((SECONDS - start)) s wall for tolerances $*" | tee -a timings.txt
}

[ -e classic-area.yaml ] || roughuq init classic-area
[ -e classic-clusters.yaml ] || roughuq init classic-clusters
: > timings.txt
if [ -n "$AREA_TOLS$AREA_EXTRA_TOLS" ]; then
    # shellcheck disable=SC2086  # the tolerance lists are meant to split
    table area classic_area.h5 classic-area.yaml $AREA_TOLS
    start=$SECONDS
    for tol in $AREA_EXTRA_TOLS; do
        run mlmc classic_area.h5 "$tol"
        run mc classic_area.h5 "$tol"
    done
    echo "area, eps = $AREA_EXTRA_TOLS: $((SECONDS - start)) s wall (after the table)" | tee -a timings.txt
fi
if [ -n "$CLUSTER_TOLS" ]; then
    # shellcheck disable=SC2086
    table clusters classic_clusters.h5 classic-clusters.yaml $CLUSTER_TOLS
fi

status=0
if [ -n "$AREA_TOLS$AREA_EXTRA_TOLS" ]; then
    python "$here/classic_tables.py" classic_area.h5 --reference "$reference" --variant contact_area \
        --json table_area.json | tee table_area.md || status=1
    roughuq report classic_area.h5 --plots figures_area > /dev/null
fi
if [ -n "$CLUSTER_TOLS" ]; then
    python "$here/classic_tables.py" classic_clusters.h5 --reference "$reference" --variant clusters \
        --json table_clusters.json | tee table_clusters.md || status=1
    roughuq report classic_clusters.h5 --plots figures_clusters > /dev/null
fi
cat timings.txt
exit "$status"
