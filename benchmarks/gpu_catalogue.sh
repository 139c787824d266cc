#!/usr/bin/env bash
# The catalogue's recipes and scores on one GPU (issue 42, point 6) and Air3D's formal certificate
# (issue 43), side by side in one session on a CUDA machine: each job alone leaves most of the GPU
# idle, so they run at once.
#
#   OUT=results DEADLINE=300 bash benchmarks/gpu_catalogue.sh [RECIPES]
#
# - trains each recipe of benchmarks/catalogue_recipes.py in RECIPES (comma-separated; default the
#   four not trained yet) on the GPU, by the same step count as on the CPU, resuming any run already
#   in runs/catalogue; each stops with a checkpoint at DEADLINE seconds (SIGTERM), to resume later;
# - scores the shipped 12D model by the card protocol (100k states, 1M fresh for the certificates)
#   and, capped by the pairwise union, under the greedy policy (EVALUATE=0 skips both);
# - certifies Air3D formally at the LEVELS (benchmarks/certify_study.py, CERT_SECONDS a level) and
#   re-checks each certificate with `reach certify --check` (CERTIFY=0 skips it).
# Everything worth keeping is packed into OUT/results.tgz (split in 15 MB parts) with a summary.
set -u
OUT=${OUT:-runs/gpu-catalogue}
DEADLINE=${DEADLINE:-300}
RECIPES=${1:-multivehicle15d,narrowpassage,quadrotor,reachavoidrocketlanding}
LEVELS=${LEVELS:-0.05 0.1}
CERT_SECONDS=${CERT_SECONDS:-60}
EVALUATE=${EVALUATE:-1}
CERTIFY=${CERTIFY:-1}
DEVICE=${DEVICE:-cuda}
PY=${PY:-python3}
WORK=${WORK:-/tmp/gpu-catalogue}
export PYTHONPATH=$PWD TQDM_DISABLE=1 PYTHONUNBUFFERED=1 MPLBACKEND=Agg
mkdir -p "$OUT" "$WORK/eval" "$WORK/cert"
# a run resumed from the CPU queue names its pair grid by the absolute path it had there
[ -e /work/main ] || { mkdir -p /work && ln -s "$PWD" /work/main; }
{
    nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
    $PY -c "import torch, sys; print('torch', torch.__version__, 'python', sys.version.split()[0])"
    nproc
} >"$WORK/device.txt"
start=$(date +%s)
train_pids=()
for recipe in ${RECIPES//,/ }; do
    timeout -s TERM -k 60 "$DEADLINE" $PY benchmarks/catalogue_recipes.py run --threads 2 --names "$recipe" \
        --device "$DEVICE" >"$WORK/train-$recipe.log" 2>&1 &
    train_pids+=($!)
done
other_pids=()
# the GPU-only tests (CUDA graph capture, the upper bound inside it, the certifier on the device)
timeout -k 10 150 $PY -m pytest -q -p no:cacheprovider tests/test_cuda_graph.py tests/test_certify.py \
    >"$WORK/gpu-tests.log" 2>&1 &
other_pids+=($!)
if [ "$EVALUATE" = 1 ]; then
    hardware="$(head -1 "$WORK/device.txt"), $(sed -n 2p "$WORK/device.txt"), beside the catalogue's GPU trainings"
    timeout -k 30 "$((DEADLINE + 120))" $PY benchmarks/make_pretrained.py evaluate multivehicle12d --samples 100000 \
        --certify-samples 1000000 --chunk-size 262144 --pairwise runs/pair_gt.npz --device "$DEVICE" \
        --hardware "$hardware" >"$WORK/eval/card-12d.log" 2>&1 &
    other_pids+=($!)
    timeout -k 30 "$((DEADLINE + 120))" $PY -m reach --threads 2 evaluate "cap:pretrained:multivehicle12d,runs/pair_gt.npz" \
        --policy greedy --samples 100000 --certify-samples 1000000 --seed 0 --chunk-size 262144 \
        --pairwise runs/pair_gt.npz --device "$DEVICE" --out "$WORK/eval/cap-greedy-12d.csv" \
        >"$WORK/eval/cap-greedy-12d.log" 2>&1 &
    other_pids+=($!)
fi
if [ "$CERTIFY" = 1 ]; then
    (
        # shellcheck disable=SC2086
        $PY benchmarks/certify_study.py --device "$DEVICE" --levels $LEVELS --max-seconds "$CERT_SECONDS" \
            --batch 4096 --out-dir "$WORK/cert"
        for cert in "$WORK"/cert/level-*.npz; do
            /usr/bin/time -f "check wall %e s" $PY -m reach certify pretrained:air3d --check "$cert" --device "$DEVICE"
        done
    ) >"$WORK/cert/certify.md" 2>&1 &
    other_pids+=($!)
fi
for pid in "${train_pids[@]}"; do wait "$pid"; done
echo "trainings stopped after $(($(date +%s) - start)) s" >>"$WORK/device.txt"
for pid in "${other_pids[@]}"; do wait "$pid"; done
echo "all stopped after $(($(date +%s) - start)) s" >>"$WORK/device.txt"
$PY benchmarks/catalogue_recipes.py status >"$WORK/status.txt" 2>&1
runs=()
for recipe in ${RECIPES//,/ }; do runs+=("runs/catalogue/$recipe"); done
cards=(training/pretrained/*.card.json)
tar czf "$WORK/results.tgz" --exclude='*.rollouts' --exclude='*.lock' -C "$PWD" "${runs[@]}" "${cards[@]}" \
    -C "$WORK" device.txt status.txt eval cert gpu-tests.log $(cd "$WORK" && ls train-*.log)
split -b 15M -d "$WORK/results.tgz" "$OUT/results.tgz.part"
{
    cat "$WORK/device.txt" "$WORK/status.txt"
    tail -n 3 "$WORK"/gpu-tests.log "$WORK"/train-*.log
    tail -n 25 "$WORK"/eval/*.log 2>/dev/null
    cat "$WORK/cert/certify.md" 2>/dev/null
} >"$OUT/summary.txt"
ls -la "$OUT"
