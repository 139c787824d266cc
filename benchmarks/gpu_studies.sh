#!/usr/bin/env bash
# The 9D studies' runs on one GPU, many processes at once, each stopped after SECONDS and resumable.
#
# Usage: benchmarks/gpu_studies.sh OUTDIR SECONDS [train|score]
#
# The 9D training step (4x128 network, 8192 points) is launch-bound on a GPU: one process keeps the
# GPU busy for a small share of each step (measured: docs/results/benchmarks.md). So this script starts the studies'
# runs as parallel processes (one per line of JOBS below, or of the file named by $JOBS_FILE), each
# with `--device cuda`, and stops every one with SIGTERM after SECONDS (`reach train` finishes its
# step and checkpoints first). Running it again resumes every run where it stopped: the studies
# count steps, so a run trained in pieces, or partly on a CPU, trains the same schedule.
#
# `score` runs each study's score stage on the GPU instead (1M fresh states, chunks of 2^18), the
# three studies side by side. Every log lands in OUTDIR/logs.txt, each job's rate in OUTDIR/rates.txt.
set -u
out=${1:?usage: gpu_studies.sh OUTDIR SECONDS [train|score]}
secs=${2:?usage: gpu_studies.sh OUTDIR SECONDS [train|score]}
stage=${3:-train}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 TQDM_DISABLE=1 MPLBACKEND=Agg
py=${PYTHON:-python3}
b=benchmarks
if [[ -n ${JOBS_FILE:-} ]]; then
    mapfile -t jobs <"$JOBS_FILE"
elif [[ $stage == train ]]; then
    jobs=(
        # issue 18's candidate recipe: two hours of its own CPU rate (measured: docs/results/training.md)
        "$b/nine_d_ablation.py train --rows recipe --seeds 0 --minutes 120 --steps-per-minute 433"
        "$b/nine_d_ablation.py train --rows recipe --seeds 1 --minutes 120 --steps-per-minute 433"
        # the default recipe against time
        "$b/nine_d_accuracy_vs_time.py train --minutes 120 --seeds 0"
        "$b/nine_d_accuracy_vs_time.py train --minutes 120 --seeds 1"
        "$b/nine_d_accuracy_vs_time.py train --minutes 60 --seeds 0"
        "$b/nine_d_accuracy_vs_time.py train --minutes 60 --seeds 1"
        "$b/nine_d_accuracy_vs_time.py train --minutes 10,30 --seeds 0"
        "$b/nine_d_accuracy_vs_time.py train --minutes 10,30 --seeds 1"
        # the ablation's rows (its baseline is the time study's 10-minute run)
        "$b/nine_d_ablation.py train --rows upper-bound,lower-bound,mpc-labels --seeds 0"
        "$b/nine_d_ablation.py train --rows upper-bound,lower-bound,mpc-labels --seeds 1"
        "$b/nine_d_ablation.py train --rows both-bounds,zero-level --seeds 0"
        "$b/nine_d_ablation.py train --rows both-bounds,zero-level --seeds 1"
        # the longer layout study
        "$b/nine_d_layouts.py train --layouts ssrsl,rsrsl,rrrsl --seeds 0"
        "$b/nine_d_layouts.py train --layouts srrrl,ssssl,rrrrl --seeds 0"
        "$b/nine_d_layouts.py train --layouts ssrsl,rsrsl,rrrsl --seeds 1"
        "$b/nine_d_layouts.py train --layouts srrrl,ssssl,rrrrl --seeds 1"
    )
else
    score="--device cuda --chunk-size 262144"
    jobs=(
        "$b/nine_d_accuracy_vs_time.py score $score"
        "$b/nine_d_ablation.py score --rows upper-bound,lower-bound,mpc-labels,both-bounds,zero-level $score"
        "$b/nine_d_ablation.py score --rows recipe --minutes 120 --steps-per-minute 433 $score"
        "$b/nine_d_layouts.py score $score"
    )
fi

t0=$(date +%s)
pids=()
for i in "${!jobs[@]}"; do
    job=${jobs[$i]}
    [[ -z $job || $job == \#* ]] && continue
    [[ $stage == train ]] && job="$job --device cuda"
    # SIGTERM checkpoints a training run; the kill 120 s later is for a run stuck elsewhere
    # shellcheck disable=SC2086
    timeout -k 120 "$secs" $py $job >"$out/job$i.log" 2>&1 &
    pids+=($!)
    echo "job$i: $job" >>"$out/jobs.txt"
done
wait "${pids[@]}"
echo "all jobs ended after $(( $(date +%s) - t0 )) s" >>"$out/jobs.txt"
for log in "$out"/job*.log; do
    echo "=== $log"
    cat "$log"
done >"$out/logs.txt"
rm -f "$out"/job*.log
# each run's steps and measured rate, read from its checkpoint record
for record in studies/*/runs/*/checkpoint.json; do
    [[ -e $record ]] && $py -c "import json, sys; r = json.load(open(sys.argv[1])); \
print(sys.argv[1].split('/')[-2], r.get('steps'), round(r.get('wall_time_s', 0), 1))" "$record"
done >"$out/rates.txt" 2>&1
exit 0
