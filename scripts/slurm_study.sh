#!/usr/bin/env bash
# A whole MLMC run on a SLURM cluster with job arrays: each array task computes
# one shard with `roughuq sample`; a dependent job merges and plans the next
# round. Submit from a login node in the study's directory:
#
#   scripts/slurm_study.sh CONFIG TOL [STUDY] [CHUNK]
#
# The study file must be on a shared file system. Each task uses one core
# (solver.threads = 1); adjust the #SBATCH lines to your site.
set -euo pipefail
config="$1"; tol="$2"; study="${3:-results.h5}"; chunk="${4:-20}"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
shards="${study%.h5}.shards"
mkdir -p "$shards" logs

if [ ! -f "$study" ]; then
    # Screening is small: one job, all its cores.
    srun --ntasks=1 --cpus-per-task=8 roughuq screen "$config" --out "$study" --workers 8
fi

# One line per shard: "STAGE LEVEL A:B".
roughuq mlmc --study "$study" --tol "$tol" --plan --shards "$chunk" > "$shards/tasks.txt"

n=$(wc -l < "$shards/tasks.txt")
if [ "$n" -eq 0 ]; then
    roughuq mlmc --study "$study" --tol "$tol"   # everything is stored: finish
    exit 0
fi

array=$(sbatch --parsable --array=1-"$n" --ntasks=1 --cpus-per-task=1 --output=logs/shard-%A_%a.out <<EOS
#!/usr/bin/env bash
read -r stage level indices < <(sed -n "\${SLURM_ARRAY_TASK_ID}p" "$shards/tasks.txt")
roughuq sample --study "$study" --stage "\$stage" --level "\$level" --indices "\$indices" \
    --out "$shards/\$SLURM_ARRAY_JOB_ID-\$SLURM_ARRAY_TASK_ID.h5" --workers 1 --quiet
EOS
)
# When every shard is done (or failed: rerunning plans what is still missing),
# merge them and submit the next round from this same script.
sbatch --dependency=afterany:"$array" --ntasks=1 --output=logs/merge-%j.out <<EOS
#!/usr/bin/env bash
set -e
shopt -s nullglob
files=("$shards/$array"-*.h5)
[ \${#files[@]} -eq 0 ] || roughuq merge "\${files[@]}" --into "$study"
bash "$here/slurm_study.sh" "$config" "$tol" "$study" "$chunk"
EOS
