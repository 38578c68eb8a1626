#!/usr/bin/env bash
# A whole MLMC study on a SLURM cluster with job arrays. Run it once from a
# login node, in a directory the compute nodes share; it submits jobs and
# returns, and the jobs carry the study to its end:
#
#   scripts/slurm_study.sh [OPTIONS] CONFIG TOL [STUDY] [CHUNK]
#
#   CONFIG  study config (YAML)          TOL    as for `roughuq mlmc --tol`
#   STUDY   study file (results.h5)      CHUNK  samples per shard (20)
#
# 1. Screening: one job, `roughuq screen` on --cpus cores (skipped when the
#    study is already screened).
# 2. A round: `roughuq mlmc --plan --shards CHUNK --resources` lists the
#    missing samples as shards, each with its estimated wall time and memory
#    (from the stored samples' speed and the cost model, see
#    rough_uq/study/resources.py); one job array per level computes them, one core
#    per task, with --time and --mem = estimate x factor.
# 3. A job that waits for all arrays of the round (afterany) runs this script
#    again: it merges the shards that were written and plans the next round.
#    A task that died (killed, timed out, node lost) wrote no shard, so its
#    samples are planned again, with the time factor doubled; after --retries
#    rounds in a row with failures the chain stops with a message.
# 4. When nothing is missing, `roughuq mlmc` writes the estimate into the
#    study (its output is in the last logs/next-*.out).
#
# Options; each has an environment variable (in brackets), an option wins:
#   --cpus N          cores of the screening job [RUQ_CPUS]; default: the
#                     fewest CPUs of a node of the partition (sinfo), else 1
#   --partition P     partition of every job [RUQ_PARTITION]; default: the
#                     site's (sbatch also reads SBATCH_PARTITION)
#   --account A       account of every job [RUQ_ACCOUNT]
#   --time-factor F   shard --time = F x estimate [RUQ_TIME_FACTOR] (3)
#   --mem-factor F    shard --mem = F x estimate [RUQ_MEM_FACTOR] (1.5)
#   --min-time MIN    shortest shard --time, minutes [RUQ_MIN_TIME] (5)
#   --max-time MIN    longest shard --time, minutes [RUQ_MAX_TIME]; default:
#                     the partition's limit (sinfo), else none
#   --screen-time MIN, --screen-mem MB   of the screening job
#                     [RUQ_SCREEN_TIME, RUQ_SCREEN_MEM]; default: the site's
#   --next-time MIN   of the merge-and-plan jobs [RUQ_NEXT_TIME]; default: the site's
#   --retries N       rounds in a row with failed tasks before stopping [RUQ_RETRIES] (3)
#   --array-max N     most tasks per job array (MaxArraySize - 1) [RUQ_ARRAY_MAX] (1000)
#   --sbatch-args S   more options for every sbatch, e.g. "--qos=short" [RUQ_SBATCH_ARGS]
#   ROUGHUQ           the roughuq command (default `roughuq`), e.g. "python -m rough_uq.cli"
#
# Logs go to logs/ in the current directory; shards and tasks lists to
# STUDY's name with .shards. Run it again with the same arguments to resume
# a chain that stopped (it merges what is there and plans the rest); never
# run two chains on one study at once.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"

cpus="${RUQ_CPUS:-}"; partition="${RUQ_PARTITION:-}"; account="${RUQ_ACCOUNT:-}"
time_factor="${RUQ_TIME_FACTOR:-3}"; mem_factor="${RUQ_MEM_FACTOR:-1.5}"
min_time="${RUQ_MIN_TIME:-5}"; max_time="${RUQ_MAX_TIME:-}"
screen_time="${RUQ_SCREEN_TIME:-}"; screen_mem="${RUQ_SCREEN_MEM:-}"; next_time="${RUQ_NEXT_TIME:-}"
retries="${RUQ_RETRIES:-3}"; array_max="${RUQ_ARRAY_MAX:-1000}"; sbatch_args="${RUQ_SBATCH_ARGS:-}"
read -r -a ruq <<< "${ROUGHUQ:-roughuq}"

die() { echo "slurm_study.sh: $*" >&2; exit 1; }
positional=()
while [ $# -gt 0 ]; do
    case "$1" in
        --cpus) cpus="$2"; shift 2 ;;
        --partition) partition="$2"; shift 2 ;;
        --account) account="$2"; shift 2 ;;
        --time-factor) time_factor="$2"; shift 2 ;;
        --mem-factor) mem_factor="$2"; shift 2 ;;
        --min-time) min_time="$2"; shift 2 ;;
        --max-time) max_time="$2"; shift 2 ;;
        --screen-time) screen_time="$2"; shift 2 ;;
        --screen-mem) screen_mem="$2"; shift 2 ;;
        --next-time) next_time="$2"; shift 2 ;;
        --retries) retries="$2"; shift 2 ;;
        --array-max) array_max="$2"; shift 2 ;;
        --sbatch-args) sbatch_args="$2"; shift 2 ;;
        -h|--help) sed -n '2,/^set -euo/p' "${BASH_SOURCE[0]}" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
        --) shift; positional+=("$@"); break ;;
        -*) die "unknown option $1 (see --help)" ;;
        *) positional+=("$1"); shift ;;
    esac
done
[ ${#positional[@]} -ge 2 ] && [ ${#positional[@]} -le 4 ] \
    || die "usage: slurm_study.sh [OPTIONS] CONFIG TOL [STUDY] [CHUNK]"
absolute() { case "$1" in /*) echo "$1" ;; *) echo "$PWD/$1" ;; esac; }
config="$(absolute "${positional[0]}")"; tol="${positional[1]}"
study="$(absolute "${positional[2]:-results.h5}")"; chunk="${positional[3]:-20}"
# A typo in the config fails here, not in the first job after a queue wait.
"${ruq[@]}" validate "$config" > /dev/null || die "$config is not a valid config (see above); nothing was submitted"
shards="${study%.h5}.shards"; logs="$PWD/logs"; state="$shards/submitted"
mkdir -p "$shards" logs

# Options every job gets; a command line as text, for the job scripts.
common=(--parsable)
[ -z "$partition" ] || common+=(--partition="$partition")
[ -z "$account" ] || common+=(--account="$account")
read -r -a extra <<< "$sbatch_args"
common+=("${extra[@]}")
quoted() { local q; q="$(printf '%q ' "$@")"; echo "${q% }"; }
roughuq="$(quoted "${ruq[@]}")"

has_sinfo() { command -v sinfo > /dev/null 2>&1; }
sinfo_lines() { sinfo -h ${partition:+-p "$partition"} -o "$1" 2> /dev/null || true; }
# A SLURM time ([D-]HH:MM:SS, MM:SS, MM, "infinite") in whole minutes; empty if unlimited.
minutes() {
    local t="$1" days=0 h=0 m=0 s=0
    case "$t" in ''|infinite|UNLIMITED|unlimited) return ;; esac
    if [[ "$t" == *-* ]]; then days="${t%%-*}"; t="${t#*-}"; fi
    IFS=: read -r -a p <<< "$t"
    case ${#p[@]} in
        1) if [ "$days" -gt 0 ]; then h="${p[0]}"; else m="${p[0]}"; fi ;;
        2) if [ "$days" -gt 0 ]; then h="${p[0]}"; m="${p[1]}"; else m="${p[0]}"; s="${p[1]}"; fi ;;
        *) h="${p[0]}"; m="${p[1]}"; s="${p[2]}" ;;
    esac
    echo $(( days * 1440 + 10#$h * 60 + 10#$m + (10#$s + 59) / 60 ))
}
if [ -z "$cpus" ]; then   # the smallest node, so the screening job fits on any
    ! has_sinfo || cpus="$(sinfo_lines %c | tr -d '+ ' | { grep -E '^[0-9]+$' || true; } | sort -n | head -n 1)"
    cpus="${cpus:-1}"
fi
if [ -z "$max_time" ] && has_sinfo; then   # the partition's (or the default partition's) limit
    limit="$(sinfo_lines '%P %l' | awk -v p="$partition" \
        '{ name = $1; is_default = sub(/\*$/, "", name) } (p == "" && is_default) || name == p { print $2; exit }')"
    max_time="$(minutes "$limit")"
fi

# The jobs that run this script again get every setting explicitly (a site
# may not pass the environment on to jobs).
resolved=(--cpus "$cpus" --time-factor "$time_factor" --mem-factor "$mem_factor" --min-time "$min_time"
          --retries "$retries" --array-max "$array_max" --sbatch-args "$sbatch_args")
for pair in partition:"$partition" account:"$account" max-time:"$max_time" screen-time:"$screen_time" \
            screen-mem:"$screen_mem" next-time:"$next_time"; do
    [ -z "${pair#*:}" ] || resolved+=(--"${pair%%:*}" "${pair#*:}")
done
rerun="cd $(quoted "$PWD") && ROUGHUQ=$(quoted "${ROUGHUQ:-roughuq}") exec bash $(quoted "$here/slurm_study.sh" \
    "${resolved[@]}" -- "$config" "$tol" "$study" "$chunk")"

is_screened() {
    [ -f "$study" ] && "${ruq[@]}" report "$study" --json 2> /dev/null | grep -q '"seconds_per_cost"'
}
submit_next() {   # a job that runs this script again once jobs $1 are over, however they ended
    local opts=("${common[@]}" --dependency="afterany:$1" --ntasks=1 --cpus-per-task=1
                --job-name=roughuq-next --output="$logs/next-%j.out")
    [ -z "$next_time" ] || opts+=(--time="$next_time")
    sbatch "${opts[@]}" <<EOS > /dev/null
#!/usr/bin/env bash
$rerun
EOS
}

# What the last submission left: merge every complete shard (a task killed
# while writing leaves only a .partial-* file), count the failures.
shopt -s nullglob
failed=0
files=("$shards"/shard-*.h5)
if [ ${#files[@]} -gt 0 ]; then
    "${ruq[@]}" merge "${files[@]}" --into "$study"
    rm -f "${files[@]}"
fi
screen_failed=0   # failed rounds so far if the screening has to be submitted (again)
if [ -f "$state" ]; then
    read -r what expected failed_before < "$state"
    rm -f "$state" "$shards"/shard-*.partial-*   # the jobs are over: leftovers of killed tasks
    if [ "$what" = screening ]; then
        screen_failed=$((failed_before + 1))
    elif [ ${#files[@]} -lt "$expected" ]; then
        failed=$((failed_before + 1))
        echo "slurm_study.sh: $((expected - ${#files[@]})) of $expected shards failed (logs in $logs);" \
             "planning them again" >&2
    fi
fi
give_up() { die "$retries rounds in a row had failed jobs; see $logs, fix, and run the same command again"; }
[ "$failed" -lt "$retries" ] || give_up

submit_screening() {
    failed=$screen_failed
    [ "$failed" -lt "$retries" ] || give_up
    [ "$failed" -eq 0 ] || echo "slurm_study.sh: the screening is not complete (logs in $logs); trying again" >&2
    local opts=("${common[@]}" --ntasks=1 --cpus-per-task="$cpus" --job-name=roughuq-screen
                --output="$logs/screen-%j.out")
    [ -z "$screen_time" ] || opts+=(--time="$screen_time")
    [ -z "$screen_mem" ] || opts+=(--mem="$screen_mem")
    echo "screening 1 $failed" > "$state"
    job=$(sbatch "${opts[@]}" <<EOS
#!/usr/bin/env bash
exec $roughuq screen $(quoted "$config") --out $(quoted "$study") --workers "\${SLURM_CPUS_PER_TASK:-1}"
EOS
)
    submit_next "${job%%;*}"
    echo "submitted the screening (job ${job%%;*}, --cpus-per-task=$cpus)"
}
[ -f "$study" ] || { submit_screening; exit 0; }

# One line per shard: "STAGE LEVEL A:B SECONDS MIB". The plan fails on a
# study whose screening is not complete (a screening job that died).
if ! plan="$("${ruq[@]}" mlmc --study "$study" --tol "$tol" --plan --shards "$chunk" --resources)"; then
    is_screened && die "planning failed (message above)"
    submit_screening
    exit 0
fi
if [ -z "$plan" ]; then
    # Everything is stored, the estimate too (status 3: tolerance not met, result stored).
    "${ruq[@]}" mlmc --study "$study" --tol "$tol" --quiet || [ $? -eq 3 ]
    exit 0
fi

# One job array per level (its tasks need about the same time and memory),
# in blocks of at most array_max tasks.
scale=$(( 1 << failed ))   # more time after failed rounds
n_total=0; arrays=()
for level in $(awk '{ print $2 }' <<< "$plan" | sort -un); do
    tasks="$shards/tasks-l$level.txt"
    awk -v l="$level" '$2 == l { print $1, $2, $3 }' <<< "$plan" > "$tasks"
    read -r n seconds mib < <(awk -v l="$level" \
        '$2 == l { n++; if ($4 > s) s = $4; if ($5 > m) m = $5 } END { print n, s, m }' <<< "$plan")
    time=$(awk -v s="$seconds" -v f="$time_factor" -v k="$scale" \
        'BEGIN { t = s * f * k / 60; print (t == int(t)) ? t : int(t) + 1 }')
    if [ -n "$max_time" ] && [ "$time" -gt "$max_time" ]; then
        echo "slurm_study.sh: shards of level $level may need $time min, more than the limit $max_time min;" \
             "capped (a smaller CHUNK gives shorter shards)" >&2
    fi
    [ "$time" -ge "$min_time" ] || time="$min_time"
    [ -z "$max_time" ] || [ "$time" -le "$max_time" ] || time="$max_time"
    mem=$(awk -v m="$mib" -v f="$mem_factor" 'BEGIN { x = m * f; print (x == int(x)) ? x : int(x) + 1 }')
    for ((offset = 0; offset < n; offset += array_max)); do
        size=$(( n - offset < array_max ? n - offset : array_max ))
        job=$(sbatch "${common[@]}" --array=1-"$size" --ntasks=1 --cpus-per-task=1 --time="$time" --mem="${mem}M" \
              --job-name=roughuq-l"$level" --output="$logs/shard-%A_%a.out" <<EOS
#!/usr/bin/env bash
set -euo pipefail
read -r stage level indices < <(sed -n "\$(( $offset + SLURM_ARRAY_TASK_ID ))p" $(quoted "$tasks"))
exec $roughuq sample --study $(quoted "$study") --stage "\$stage" --level "\$level" --indices "\$indices" \\
    --out $(quoted "$shards")/shard-"\$stage-\$level-\${indices%%:*}".h5 --workers 1 --quiet
EOS
)
        arrays+=("${job%%;*}")
    done
    n_total=$((n_total + n))
    echo "level $level: $n shards, --time=$time min --mem=${mem}M"
done
echo "round $n_total $failed" > "$state"
dependency="$(IFS=:; echo "${arrays[*]}")"
submit_next "$dependency"
echo "submitted $n_total shards in job arrays ${arrays[*]}; the next round starts when they are over"
