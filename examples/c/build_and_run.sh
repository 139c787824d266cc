#!/usr/bin/env bash
# The C example end to end: export Air3D's switch filter as C (reach export --c), compile it into
# filter_one_state with the system's C compiler, and filter a few states. Needs reach installed
# (for the export) and cc; the program itself needs only the C library.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
build="${REACH_C_BUILD:-$here/build}"
mkdir -p "$build"
reach --threads 1 export pretrained:air3d --kind switch --dt 0.05 --out "$build/air3d-switch.onnx" --c "$build/filter.c"
"${CC:-cc}" -O3 -march=native -fno-math-errno -fno-trapping-math -I "$build" -o "$build/filter_one_state" \
    "$here/filter_one_state.c" -lm
run() { echo "\$ filter_one_state $*"; "$build/filter_one_state" "$@" || echo "exit status $?"; }
run 1.1 0.1 0 0 1      # 0.1 m apart, head-on: the filter intervenes
run 1.1 0.9 0.9 0 1    # far apart: the nominal input is kept
run 1.1 5 0 0 1        # outside the domain: the backup input, whatever the value says
run 1.1 nan 0 0 1      # refused: NaN in the state
run 2 0.1 0 0 1        # refused: the time-to-go lies outside the value function's range
