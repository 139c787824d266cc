#!/usr/bin/env bash
# Every command of docs/custom_system.md, in order: three systems defined outside the package
# (examples/my_systems.py) through the grid solver, training, verification, filters and a sweep.
#
# Usage (from the repository root): bash examples/tutorial.sh [OUT]   (default OUT: runs/tutorial)
# FROM=STEP bash examples/tutorial.sh skips the steps before STEP (e.g. FROM=avoid-sweep).
# Output: OUT/*.log, one per step, and the files the docs page shows. The avoid systems took 23
# minutes on a 2-core machine shared with a background training run, DubinsGap about 13 more.
set -euo pipefail
out=${1:-runs/tutorial}
mkdir -p "$out"
export PYTHONPATH="examples${PYTHONPATH:+:$PYTHONPATH}" TQDM_DISABLE=1
from=${FROM:-}
step() {
    local name=$1; shift
    if [[ -n $from && $name != "$from" ]]; then echo "skipping $name"; return; fi
    from=""
    echo "\$ $*" | tee "$out/$name.log"
    "$@" 2>&1 | tee -a "$out/$name.log"
}

# --- DubinsAvoid: 3D, one control, wind on both positions
step avoid-grid reach groundtruth my_systems:DubinsAvoid --grid 101 --out "$out/avoid_gt.npz" --plot "$out/avoid_gt.png"
step avoid-train reach train --system my_systems:DubinsAvoid --steps 3000 --seed 0 \
    --groundtruth "$out/avoid_gt.npz" --out "$out/avoid"
step avoid-evaluate reach evaluate "$out/avoid" "$out/avoid_gt.npz" --system my_systems:DubinsAvoid \
    --ground-truth "$out/avoid_gt.npz" --samples 20000 --scenario-samples 0 --robust-samples 0 \
    --out "$out/avoid_eval.csv"
step avoid-filter reach filter-eval --policy gradient "$out/avoid_gt.npz" "$out/avoid" --system my_systems:DubinsAvoid \
    --filters switch,lookahead,smooth --pursuer worst-case --adversary "$out/avoid_gt.npz" \
    --start-outside "$out/avoid_gt.npz" --episodes 500 --out "$out/avoid_filter.csv" --gif "$out/avoid_filter.gif"
step avoid-sweep reach sweep --system my_systems:DubinsAvoid --layouts ssssl,rrrsl --seeds 1 --steps 500 \
    --snapshots 2 --grid 51 --out "$out/avoid_sweep"

# --- DubinsAccel: 4D, two controls (turn rate, acceleration), wind on both positions
step accel-grid reach groundtruth my_systems:DubinsAccel --grid 31 --out "$out/accel_gt.npz"
step accel-train reach train --system my_systems:DubinsAccel --steps 3000 --seed 0 --out "$out/accel"
step accel-evaluate reach evaluate "$out/accel" "$out/accel_gt.npz" --system my_systems:DubinsAccel \
    --ground-truth "$out/accel_gt.npz" --samples 20000 --scenario-samples 0 --robust-samples 0 \
    --out "$out/accel_eval.csv"
step accel-filter reach filter-eval --policy gradient "$out/accel_gt.npz" "$out/accel" --system my_systems:DubinsAccel \
    --filters switch,lookahead,smooth --pursuer worst-case --adversary "$out/accel_gt.npz" \
    --start-outside "$out/accel_gt.npz" --nominal my_systems:cruise --episodes 500 --out "$out/accel_filter.csv"

# --- DubinsGap: a reach-avoid problem (reach the goal through the gap, against the wind)
step gap-grid reach groundtruth my_systems:DubinsGap --grid 101 --out "$out/gap_gt.npz" --plot "$out/gap_gt.png"
step gap-train reach train --system my_systems:DubinsGap --steps 3000 --seed 0 \
    --groundtruth "$out/gap_gt.npz" --out "$out/gap"
step gap-evaluate reach evaluate "$out/gap" "$out/gap_gt.npz" --system my_systems:DubinsGap \
    --ground-truth "$out/gap_gt.npz" --samples 20000 --scenario-samples 20000 --robust-samples 0 \
    --out "$out/gap_eval.csv"
step gap-filter reach filter-eval --policy gradient "$out/gap_gt.npz" "$out/gap" --system my_systems:DubinsGap \
    --filters switch,lookahead --pursuer worst-case --adversary "$out/gap_gt.npz" \
    --start-outside "$out/gap_gt.npz" --nominal my_systems:head_for_goal --episodes 500 \
    --out "$out/gap_filter.csv" --gif "$out/gap_filter.gif"
step gap-sweep reach sweep --system my_systems:DubinsGap --layouts ssssl,rrrsl --seeds 1 --steps 500 \
    --snapshots 2 --grid 51 --out "$out/gap_sweep"
step gap-python python examples/reach_avoid_tour.py "$out/gap-python"
