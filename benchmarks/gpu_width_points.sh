#!/usr/bin/env bash
# Width and points per step at an equal GPU wall budget (issue 63, point 3: "width and points per step
# are the ones left untried" for the 12D and 15D fleets). Each variant trains alone on the GPU, one
# after the other, for the same wall budget (the budget drives the cosine schedule and the curriculum,
# so every variant sees its whole schedule; the residual is not compiled, since a compilation inside
# the first step would take a share of a short budget); then one card-protocol evaluation per variant, all at
# once, on the same states (seed 0).
#
#   OUT=results BUDGET=100 SYSTEM=multivehicle15d VARIANTS="128x8192 256x32768 512x65536" \
#       bash benchmarks/gpu_width_points.sh
#
# A variant is WIDTHxPOINTS. The N-car fleets (9D, 12D, 15D) train under the union of pairwise BRTs of
# the pair grid PAIRWISE (--upper-bound, as the catalogue recipes do) and are scored against it (solve
# it first: reach groundtruth relativepair --grid 101 --out runs/pair_gt.npz, and carry it); any other
# system trains and is scored without one. OUT gets summary.txt (each run's steps, wall time and the
# scores' table) and runs.tgz (split in 15 MB parts): the run directories, the evaluations and the logs.
# Smoke run on a CPU: DEVICE=cpu BUDGET=10 SAMPLES=500 SCENARIO=1000 VARIANTS="32x512 64x1024".
set -u
OUT=${OUT:-runs/width-points}
SYSTEM=${SYSTEM:-multivehicle15d}
BUDGET=${BUDGET:-100}
VARIANTS=${VARIANTS:-128x8192 256x32768 512x65536}
SAMPLES=${SAMPLES:-100000}
SCENARIO=${SCENARIO:-1000000}
DEVICE=${DEVICE:-cuda}
PAIRWISE=${PAIRWISE:-runs/pair_gt.npz}
PY=${PY:-python3}
WORK=${WORK:-/tmp/width-points}
EXTRA=${EXTRA:-} # more reach train options for every variant, e.g. "--tf32" (word-split)
export PYTHONPATH=$PWD TQDM_DISABLE=1 PYTHONUNBUFFERED=1 MPLBACKEND=Agg
# refused before any training (a lease's minutes are spent on a bad variant otherwise)
[[ "$BUDGET" =~ ^[1-9][0-9]*$ ]] || { echo "gpu_width_points.sh: BUDGET must be whole seconds > 0, got '$BUDGET'" >&2; exit 2; }
[ -n "${VARIANTS// /}" ] || { echo "gpu_width_points.sh: VARIANTS is empty" >&2; exit 2; }
for variant in $VARIANTS; do
    [[ "$variant" =~ ^[1-9][0-9]*x[1-9][0-9]*$ ]] ||
        { echo "gpu_width_points.sh: a variant is WIDTHxPOINTS (e.g. 256x32768), got '$variant'" >&2; exit 2; }
done
mkdir -p "$OUT" "$WORK"
{
    nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
    $PY -c "import torch, sys; print('torch', torch.__version__, 'python', sys.version.split()[0])"
    echo "cores $(nproc); budget ${BUDGET}s a variant; $SYSTEM; options: ${EXTRA:-none}; $(date -u +%FT%TZ)"
} | tee "$OUT/summary.txt"
# the N-car fleets train under the union of pairwise BRTs and are scored against it; other systems have no pair grid
pairwise=()
upper=()
case "$SYSTEM" in multivehicle9d | multivehicle12d | multivehicle15d)
    pairwise=(--pairwise "$PAIRWISE")
    upper=(--upper-bound "$PAIRWISE")
    ;;
esac
runs=()
for variant in $VARIANTS; do
    width=${variant%x*}
    points=${variant#*x}
    run=$WORK/w$width-p$points
    rm -rf "$run"
    start=$(date +%s)
    timeout -k 20 $((BUDGET + 60)) $PY -m reach train --system "$SYSTEM" --width "$width" --points "$points" \
        --budget "${BUDGET}s" "${upper[@]}" --compile off --seed 0 --device "$DEVICE" $EXTRA \
        --out "$run" >"$WORK/train-w$width-p$points.log" 2>&1
    rc=$?
    [ "$rc" = 0 ] || tail -5 "$WORK/train-w$width-p$points.log" >>"$OUT/summary.txt"
    # the run's own record: steps and training seconds (compilation and graph capture included)
    $PY - "$run" "$variant" "$rc" "$(($(date +%s) - start))" <<'EOF' | tee -a "$OUT/summary.txt"
import json, sys
from pathlib import Path
run, variant, rc, wall = sys.argv[1:]
path, metrics = Path(run) / "checkpoint.json", Path(run) / "metrics.jsonl"
s = json.loads(path.read_text()) if path.exists() else {}
last = json.loads(metrics.read_text().splitlines()[-1]) if metrics.exists() else {}
print(f"{variant}: exit {rc}, process {wall} s, steps {s.get('steps')}, training {s.get('wall_time_s', 0):.1f} s, "
      f"last logged steps/s {last.get('steps_per_s')}, loss {last.get('loss')}, pde {last.get('pde')}")
EOF
    runs+=("$run")
done
pids=()
for run in "${runs[@]}"; do
    name=$(basename "$run")
    timeout -k 10 200 $PY -m reach evaluate "$run" --system "$SYSTEM" --samples "$SAMPLES" \
        --scenario-samples "$SCENARIO" --seed 0 "${pairwise[@]}" --device "$DEVICE" \
        --out "$WORK/eval-$name.csv" >"$WORK/eval-$name.log" 2>&1 &
    pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid"; done
for run in "${runs[@]}"; do
    name=$(basename "$run")
    echo "## $name" >>"$OUT/summary.txt"
    cat "$WORK/eval-$name.md" >>"$OUT/summary.txt" 2>/dev/null || tail -5 "$WORK/eval-$name.log" >>"$OUT/summary.txt"
done
tar czf "$WORK/runs.tgz" -C "$WORK" --exclude=snapshots $(cd "$WORK" && ls -d w*-p* eval-* train-*) 2>/dev/null
split -b 15M -d "$WORK/runs.tgz" "$OUT/runs.tgz."
cat "$OUT/summary.txt"
