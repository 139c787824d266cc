#!/usr/bin/env bash
# First CUDA run of the toolkit: does it run on a GPU, and what does the 9D recipe cost there?
#
# Usage: benchmarks/cuda_check.sh OUTDIR [STAGE...]   (stages: tests pair train score air3d;
#        default all of them)
# TRAIN_SECONDS (default 300) caps the 9D training's wall time; TRAIN_ARGS adds options to it
# (e.g. "--points 65536"); RUN names its run directory (default runs/gpu9d).
#
# Steps (each capped by `timeout`, each log in OUTDIR):
#   env.txt        GPU, driver, Python and torch versions
#   tests.txt      the tests parametrised over devices (tests/conftest.py adds cuda when present)
#   pair.log       the union of pairwise BRTs for the 9D checks, solved on the GPU (101^3)
#   train.log      the 9D default recipe (reach train --system multivehicle9d) on the GPU, for the
#                  36,917 steps that the 40-minute CPU run of issue 18 trained, with 4 snapshots
#   evaluate.*     reach evaluate on the GPU: 100k states, 1M fresh states for the delta-level and
#                  robust certificates, the pairwise union; the final network and every snapshot
#   air3d.log      the Air3D 101^3 grid to t = 1.1 on the GPU: compiled (first run, empty cache;
#                  second run) and eager
#   gpu9d.tar.gz   the trained run directory
# Needs the package importable (pip install -e . or PYTHONPATH) and a CUDA torch.
set -u
out=${1:?usage: cuda_check.sh OUTDIR [STAGE...]}
shift
stages=" ${*:-tests pair train score air3d} "
train_s=${TRAIN_SECONDS:-300}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 TQDM_DISABLE=1 MPLBACKEND=Agg
py=${PYTHON:-python3}
run=${RUN:-runs/gpu9d}
pair=${PAIR:-runs/pair_gt_gpu.npz}

stamp() { date +%s%N; }
timed() {  # timed LOG SECONDS command...: run with a cap, log output and wall time
    local log=$1 cap=$2; shift 2
    local t0; t0=$(stamp)
    timeout "$cap" "$@" >"$log" 2>&1
    local rc=$?
    echo "# exit $rc, wall $(( ($(stamp) - t0) / 1000000 )) ms: $*" >>"$log"
    tail -n 4 "$log"
}

{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  $py -c "import sys, torch; print(sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name())"
  nproc; } | tee "$out/env.txt"

want() { [[ $stages == *" $1 "* ]]; }

want tests && timed "$out/tests.txt" 300 $py -m pytest -q -p no:cacheprovider tests/test_systems.py -k cuda
want pair && timed "$out/pair.log" 120 $py -m reach groundtruth relativepair --grid 101 --device cuda --out "$pair"
if want train; then
rm -rf "$run"
timed "$out/train.log" $((train_s + 120)) $py -m reach train --system multivehicle9d --device cuda \
    --steps 36917 --budget "${train_s}s" --snapshots 4 ${TRAIN_ARGS:-} --out "$run"
tar czf "$out/$(basename "$run").tar.gz" "$run"
fi
# chunks of 2^18 states: the CPU default (16384) leaves the GPU launch-bound
want score && timed "$out/evaluate.log" "${SCORE_SECONDS:-600}" $py -m reach evaluate "$run" "$run"/snapshots/*.pt \
    --device cuda --chunk-size 262144 --samples 100000 --scenario-samples 1000000 --pairwise "$pair" \
    --out "$out/evaluate.csv"
want air3d && for attempt in first second; do
    timed "$out/air3d-$attempt.log" 90 $py -m reach groundtruth air3d --grid 101 --device cuda \
        --compile on --out /tmp/air3d_gpu.npz
done
want air3d && timed "$out/air3d-eager.log" 90 $py -m reach groundtruth air3d --grid 101 --device cuda \
    --compile off --out /tmp/air3d_gpu.npz
exit 0
