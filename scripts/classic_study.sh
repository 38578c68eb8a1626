#!/usr/bin/env bash
# The classic study of SPEC section 6, reproduced with roughuq commands.
#
#   scripts/classic_study.sh [WORKDIR]
#
# Contact area (L = 2, grids from 256): screening, then MLMC and plain MC for a
# decreasing list of tolerances (percent); cluster density (L = 3, grids from
# 128, 8-connectivity): screening, then MLMC and MC at a few tolerances
# (clusters per unit area). Then the reports. Every command resumes where it
# stopped if the script is interrupted and run again. About an hour on 2 cores.
# The configs are the shipped ones (`roughuq init`), written into WORKDIR once;
# edit them there before a rerun to change the study.
set -euo pipefail
work="${1:-classic}"
mkdir -p "$work"
cd "$work"

AREA_TOLS=${AREA_TOLS:-"1.0 0.7 0.5"}
AREA_MC_TOLS=${AREA_MC_TOLS:-"1.0 0.5"}
CLUSTER_TOLS=${CLUSTER_TOLS:-"40 20 10"}
CLUSTER_MC_TOLS=${CLUSTER_MC_TOLS:-"40 20 10"}

[ -e classic-area.yaml ] || roughuq init classic-area
roughuq screen classic-area.yaml --out classic_area.h5
for tol in $AREA_TOLS; do
    roughuq mlmc --study classic_area.h5 --tol "$tol" || [ $? -eq 3 ]  # 3: tolerance not met, result stored
done
for tol in $AREA_MC_TOLS; do
    roughuq mc --study classic_area.h5 --tol "$tol" || [ $? -eq 3 ]
done

[ -e classic-clusters.yaml ] || roughuq init classic-clusters
roughuq screen classic-clusters.yaml --out classic_clusters.h5
for tol in $CLUSTER_TOLS; do
    roughuq mlmc --study classic_clusters.h5 --tol "$tol" || [ $? -eq 3 ]
done
for tol in $CLUSTER_MC_TOLS; do
    roughuq mc --study classic_clusters.h5 --tol "$tol" || [ $? -eq 3 ]
done

roughuq report classic_area.h5
roughuq report classic_clusters.h5
