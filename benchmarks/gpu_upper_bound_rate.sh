#!/usr/bin/env bash
# Steps per second of the 9D `--upper-bound` training row on a GPU, each run alone on it.
#
# Usage: benchmarks/gpu_upper_bound_rate.sh OUTDIR [STEPS] [PAIR]
#
# Two runs of `reach train --system multivehicle9d --device cuda --steps STEPS` (default 2000; DEVICE=cpu to try it),
# one after the other, so each has the GPU to itself:
#   default          the default recipe (no bound)
#   upper            --upper-bound PAIR (the union of pairwise BRTs, interpolated at every step's points)
# Each run's rate is the median of the `steps_per_s` its metrics.jsonl logs after the first quarter
# of its steps (compile and warm-up excluded). PAIR defaults to runs/pair_gt.npz (solved if missing).
set -u
out=${1:?usage: gpu_upper_bound_rate.sh OUTDIR [STEPS] [PAIR]}
steps=${2:-2000}
pair=${3:-runs/pair_gt.npz}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 TQDM_DISABLE=1 MPLBACKEND=Agg
py=${PYTHON:-python3}
[[ -e $pair ]] || $py -m reach groundtruth relativepair --grid 101 --device "${DEVICE:-cuda}" --out "$pair" >"$out/pair.log" 2>&1

train() {  # train NAME [extra reach train options...]
    local name=$1; shift
    rm -rf "$out/$name"
    $py -m reach train "$@" --system multivehicle9d --device "${DEVICE:-cuda}" --steps "$steps" \
        --out "$out/$name" >"$out/$name.log" 2>&1
    echo "$name exit $?"
}

rate() {  # median steps/s after the first quarter of the run
    $py -c "
import json, statistics, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
rows = [r for r in rows if 'steps_per_s' in r and r['step'] > int(sys.argv[2]) // 4]
print(f'{sys.argv[3]}: {statistics.median(r[\"steps_per_s\"] for r in rows):.1f} steps/s '
      f'(median of {len(rows)} logged rates, steps {rows[0][\"step\"]}-{rows[-1][\"step\"]})')
" "$out/$1/metrics.jsonl" "$steps" "$1"
}

train default
train upper --upper-bound "$pair"
{ nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
  $py -c "import torch; print('torch', torch.__version__)"
  for name in default upper; do rate $name; done; } 2>&1 | tee "$out/rates.txt"
