#!/usr/bin/env bash
# The catalogue's GPU work in one call on a CUDA machine (issue 42's points 4-6, issue 43): each
# job alone leaves most of the GPU idle, so they run at once, each in its own process.
#
#   OUT=results DEADLINE=300 TRAIN=multivehicle9d EVALUATE=quadrotor SCORE=multivehicle12d \
#       bash benchmarks/gpu_catalogue.sh
#
# - TRAIN: recipes of benchmarks/catalogue_recipes.py (comma-separated) trained on the GPU by the
#   same step count as on the CPU, resuming any run already in runs/catalogue; each stops with a
#   checkpoint at DEADLINE seconds (SIGTERM), to resume later. A trained fleet of the dimension
#   study is then scored (benchmarks/dimension_study.py score) in the time left;
# - EVALUATE: shipped models scored by the card protocol (100k states, 1M fresh for the
#   certificates), which rewrites their cards (the N-car ones also against the pairwise union);
# - SCORE: fleets of the dimension study whose snapshots are scored now (their training is done);
# - CERTIFY=1: Air3D certified formally at the LEVELS (benchmarks/certify_study.py, CERT_SECONDS a
#   level), each certificate re-checked with `reach certify --check`.
# The GPU-only tests run beside them. Everything worth keeping is packed into OUT/results.tgz (split
# in 15 MB parts) with OUT/summary.txt. Carry runs/pair_gt.npz and the run directories it resumes.
set -u
OUT=${OUT:-runs/gpu-catalogue}
DEADLINE=${DEADLINE:-300}
TRAIN=${TRAIN:-}
EVALUATE=${EVALUATE:-}
SCORE=${SCORE:-}
CERTIFY=${CERTIFY:-0}
LEVELS=${LEVELS:-0.05 0.1}
CERT_SECONDS=${CERT_SECONDS:-60}
DEVICE=${DEVICE:-cuda}
PY=${PY:-python3}
WORK=${WORK:-/tmp/gpu-catalogue}
PAIRWISE=runs/pair_gt.npz
export PYTHONPATH=$PWD TQDM_DISABLE=1 PYTHONUNBUFFERED=1 MPLBACKEND=Agg
mkdir -p "$OUT" "$WORK/eval" "$WORK/cert"
# a run resumed from the CPU queue names its pair grid by the absolute path it had there
[ -e /work/main ] || { mkdir -p /work && ln -s "$PWD" /work/main; }
{
    nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
    $PY -c "import torch, sys; print('torch', torch.__version__, 'python', sys.version.split()[0])"
    nproc
} >"$WORK/device.txt"
hardware="$(head -1 "$WORK/device.txt"), $(sed -n 2p "$WORK/device.txt"), beside other GPU jobs"
start=$(date +%s)
left() { echo $((DEADLINE - ($(date +%s) - start))); }
pids=()
for recipe in ${TRAIN//,/ }; do
    (
        timeout -s TERM -k 60 "$DEADLINE" $PY benchmarks/catalogue_recipes.py run --threads 2 --names "$recipe" \
            --device "$DEVICE"
        echo "training stopped after $(($(date +%s) - start)) s"
        case "$recipe" in multivehicle9d | multivehicle12d | multivehicle15d)
            [ "$(left)" -gt 20 ] && timeout -k 10 "$(left)" $PY benchmarks/dimension_study.py score \
                --fleets "$recipe" --device "$DEVICE"
            ;;
        esac
    ) >"$WORK/train-$recipe.log" 2>&1 &
    pids+=($!)
done
for fleet in ${SCORE//,/ }; do
    timeout -k 10 "$DEADLINE" $PY benchmarks/dimension_study.py score --fleets "$fleet" --device "$DEVICE" \
        >"$WORK/score-$fleet.log" 2>&1 &
    pids+=($!)
done
# the GPU-only tests (CUDA graph capture, the upper bound inside it, the certifier on the device)
timeout -k 10 150 $PY -m pytest -q -p no:cacheprovider tests/test_cuda_graph.py tests/test_certify.py \
    >"$WORK/gpu-tests.log" 2>&1 &
pids+=($!)
for name in ${EVALUATE//,/ }; do
    pairwise=()
    case "$name" in multivehicle*) pairwise=(--pairwise "$PAIRWISE") ;; esac
    timeout -k 10 "$DEADLINE" $PY benchmarks/make_pretrained.py evaluate "$name" \
        --samples 100000 --scenario-samples 1000000 --chunk-size 262144 "${pairwise[@]}" --device "$DEVICE" \
        --out "$WORK/eval/$name.csv" --hardware "$hardware" >"$WORK/eval/card-$name.log" 2>&1 &
    pids+=($!)
done
if [ "$CERTIFY" = 1 ]; then
    (
        # shellcheck disable=SC2086
        $PY benchmarks/certify_study.py --device "$DEVICE" --levels $LEVELS --max-seconds "$CERT_SECONDS" \
            --batch 4096 --out-dir "$WORK/cert"
        for cert in "$WORK"/cert/level-*.npz; do
            /usr/bin/time -f "check wall %e s" $PY -m reach certify pretrained:air3d --check "$cert" --device "$DEVICE"
        done
    ) >"$WORK/cert/certify.md" 2>&1 &
    pids+=($!)
fi
for pid in "${pids[@]}"; do wait "$pid"; done
echo "all stopped after $(($(date +%s) - start)) s" >>"$WORK/device.txt"
$PY benchmarks/catalogue_recipes.py status >"$WORK/status.txt" 2>&1
keep=()
for recipe in ${TRAIN//,/ }; do keep+=("runs/catalogue/$recipe"); done
[ -d runs/studies/dimension ] && keep+=(runs/studies/dimension)
cards=(training/pretrained/*.card.json)
# shellcheck disable=SC2046
tar czf "$WORK/results.tgz" --exclude='*.rollouts' --exclude='*.lock' -C "$PWD" "${keep[@]}" "${cards[@]}" \
    -C "$WORK" device.txt status.txt eval cert gpu-tests.log $(cd "$WORK" && ls train-*.log score-*.log 2>/dev/null)
split -b 15M -d "$WORK/results.tgz" "$OUT/results.tgz.part"
{
    cat "$WORK/device.txt" "$WORK/status.txt"
    tail -n 3 "$WORK"/gpu-tests.log "$WORK"/train-*.log "$WORK"/score-*.log 2>/dev/null
    tail -n 25 "$WORK"/eval/*.log 2>/dev/null
    cat "$WORK/cert/certify.md" 2>/dev/null
} >"$OUT/summary.txt"
ls -la "$OUT"
