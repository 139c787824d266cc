#!/usr/bin/env bash
# Steps per second of the 9D `--upper-bound` training row on a GPU, each run alone on it.
#
# Usage: benchmarks/gpu_upper_bound_rate.sh OUTDIR [STEPS] [PAIR]
#
# Three runs of `reach train --system multivehicle9d --device cuda --steps STEPS` (default 2000; DEVICE=cpu to try it),
# one after the other, so each has the GPU to itself:
#   default          the default recipe (no bound)
#   upper-checked    --upper-bound PAIR, the union's input checks on every step (finite states, times
#                    covered; each reads a result back from the GPU): the trainer before they were
#                    skipped, restored here by patching Trainer._upper_bound_at
#   upper            --upper-bound PAIR as the trainer runs it now (check_inputs=False)
# Each run's rate is the median of the `steps_per_s` its metrics.jsonl logs after the first quarter
# of its steps (compile and warm-up excluded). PAIR defaults to runs/pair_gt.npz (solved if missing).
set -u
out=${1:?usage: gpu_upper_bound_rate.sh OUTDIR [STEPS] [PAIR]}
steps=${2:-2000}
pair=${3:-runs/pair_gt.npz}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 TQDM_DISABLE=1 MPLBACKEND=Agg
py=${PYTHON:-python3}
[[ -e $pair ]] || $py -m reach groundtruth relativepair --grid 101 --device cuda --out "$pair" >"$out/pair.log" 2>&1

train() {  # train NAME PATCH [extra reach train options...]
    local name=$1 patch=$2; shift 2
    rm -rf "$out/$name"
    $py - "$@" --system multivehicle9d --device "${DEVICE:-cuda}" --steps "$steps" --out "$out/$name" >"$out/$name.log" 2>&1 <<EOF
import sys
if "$patch" == "checked":
    import torch
    from training.trainer import Trainer

    def checked(self, x, t):
        with torch.no_grad():
            return self.upper_bound.value_where_known(x.detach(), t.detach(), check_inputs=True).to(x.dtype)

    Trainer._upper_bound_at = checked
from reach.cli import main
sys.argv[0] = "reach"
raise SystemExit(main(["train", *sys.argv[1:]]))
EOF
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

train default none
train upper-checked checked --upper-bound "$pair"
train upper none --upper-bound "$pair"
{ nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
  $py -c "import torch; print('torch', torch.__version__)"
  for name in default upper-checked upper; do rate $name; done; } 2>&1 | tee "$out/rates.txt"
