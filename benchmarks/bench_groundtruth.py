"""Grid solver performance: wall time, peak memory and throughput for Air3D (or ``--system``) to horizon 1.0.

Run: ``python benchmarks/bench_groundtruth.py`` (``--grids 51 101``; ``--quick`` for 31 only;
``--system my_systems:DubinsAccel`` with ``examples/`` on ``PYTHONPATH`` for the 4D example).
``--against hj_reachability`` compares first and second runs, each a fresh process, with
hj_reachability on Air3D 31^3-101^3 and user-defined 3D and 4D systems (``benchmarks/hj_comparison.py``),
in ``--repeats`` interleaved rounds per size (default 3) reported as medians.

Each grid is solved twice in one process when compiling: the first run includes torch.compile's
one-off compilation (from a fresh inductor cache unless ``--reuse-compile-cache``; a later process
reuses the on-disk cache), the second is the steady-state cost. Peak memory is
the process's peak resident set size (``ru_maxrss``) after each solve, which includes the Python
interpreter and torch (~0.4 GB). Accuracy is reported against the MATLAB toolbox slice when
``../shared/reference`` is present.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from groundtruth import SolverSettings, solve
from reach.systems import make_system

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "air3d_levelset_slice.npz"


def slice_error(solution) -> tuple[float, float] | None:
    if not REFERENCE.exists():
        return None
    with np.load(REFERENCE) as ref:
        x1, x2 = np.meshgrid(ref["x1"], ref["x2"], indexing="ij")
        pts = np.stack([x1, x2, np.full_like(x1, float(ref["x3"]))], axis=-1)
        v = solution.value(torch.tensor(pts, dtype=torch.float64), 1.0).numpy()
        ls = ref["LS"]
    iou = float(((v <= 0) & (ls <= 0)).sum() / ((v <= 0) | (ls <= 0)).sum())
    return float(np.abs(v - ls).max()), iou


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--grids", type=int, nargs="+", default=None, help="grid sizes (default 51 101; with --against: all)"
    )
    parser.add_argument(
        "--system", default="air3d", help="a registered system or an import path module:Class (default air3d)"
    )
    parser.add_argument("--compile", choices=["on", "off"], default="on")
    parser.add_argument("--dissipation", choices=["local", "global"], default="local")
    parser.add_argument("--tube", choices=["min_with_target", "min_over_time"], default="min_with_target")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--reuse-compile-cache", action="store_true", help="keep torch inductor's on-disk cache (default: a fresh one)"
    )
    parser.add_argument(
        "--against", choices=["hj_reachability"], default=None, help="compare with another solver (fresh processes)"
    )
    parser.add_argument("--hj-python", default=None, help="an interpreter with hj_reachability (default: install one)")
    parser.add_argument(
        "--repeats", type=int, default=3, help="with --against: interleaved rounds per size, reported as medians"
    )
    args = parser.parse_args()
    if args.against:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from hj_comparison import compare

        raise SystemExit(compare(args.quick, args.hj_python, args.grids, args.repeats))
    if not args.reuse_compile_cache:  # so that "cold" really includes compilation from scratch
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="reach-inductor-")
    if args.quick:
        args.grids = [31]
    args.grids = args.grids or [51, 101]
    system = make_system(args.system)
    print(
        f"# Ground-truth solver benchmark: {system.name}, horizon 1.0, WENO5 + {args.dissipation} LF + TVD-RK3, "
        f"CFL 0.75, float32, tube {args.tube}"
    )
    print(
        f"python {platform.python_version()}, torch {torch.__version__}, {os.cpu_count()} CPUs, "
        f"{torch.get_num_threads()} torch threads, compile={args.compile}\n"
    )
    print(
        "| grid | run | wall s | steps | steps/s | grid-points x steps / s | peak RSS GB "
        "| max abs err vs toolbox | IoU |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    runs = ["cold (includes compile)", "warm"] if args.compile == "on" else ["eager"]
    for n in args.grids:
        for run in runs:
            t0 = time.perf_counter()
            sol = solve(
                system,
                n,
                [1.0],
                settings=SolverSettings(compile=args.compile == "on", dissipation=args.dissipation, tube=args.tube),
                progress=False,
            )
            wall = time.perf_counter() - t0
            steps = sol.metadata["scheme"]["steps"]
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
            acc = slice_error(sol) if system.name == "air3d" else None
            err, iou = (f"{acc[0]:.2e}", f"{acc[1]:.4f}") if acc else ("n/a", "n/a")
            print(
                f"| {n}^{system.state_dim} | {run} | {wall:.1f} | {steps} | {steps / wall:.1f} | "
                f"{sol.grid.num_points * steps / wall:.3g} | {rss:.2f} | {err} | {iou} |"
            )


if __name__ == "__main__":
    main()
