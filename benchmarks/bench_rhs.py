"""One right-hand side of the grid solver (an RK3 stage's WENO5 derivatives, Hamiltonian and
dissipation), eager and compiled, in milliseconds.

Run: ``PYTHONPATH=examples python benchmarks/bench_rhs.py --system my_systems:DubinsAccel --grids 21 31 41``
(``--mode eager`` or ``--mode compiled`` for one of them). Each mode is timed as the solver runs it:
inside ``reach.malloc_thresholds.retained_heap`` and ``torch.inference_mode()``, on the system's failure margin, after
warm-up calls (which include compiling, from a fresh inductor cache unless
``--reuse-compile-cache``); it prints the best mean of ``--repeats`` blocks of ``--calls`` calls.
A solve makes three calls per time step. Use it to compare two versions of the solver side by side
(``PYTHONPATH=<other checkout>``), with nothing else running.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import torch

from groundtruth.grid import Grid
from groundtruth.solver import _rhs_factory
from reach.malloc_thresholds import retained_heap
from reach.systems import make_system
from reach.systems.arrays import TORCH


def time_rhs(system_name: str, n: int, compiled: bool, calls: int, repeats: int) -> tuple[float, float]:
    """(best mean ms per call, seconds of the first call, which includes any compilation)."""
    system = make_system(system_name)
    grid = Grid.for_system(system, n)
    cols = grid.columns(torch.float32, "cpu")
    v = torch.broadcast_to(system.failure_margin_columns(cols, TORCH), grid.shape).contiguous()
    bounds = [torch.as_tensor(a, dtype=torch.float32) for a in system.dissipation_columns(cols, TORCH)]
    rhs = _rhs_factory(system, grid, cols, bounds)
    if compiled:
        rhs = torch.compile(rhs)
    with retained_heap(2**31 - 1), torch.inference_mode():  # as the solver runs it
        start = time.perf_counter()
        rhs(v)
        first = time.perf_counter() - start
        for _ in range(2):
            rhs(v)
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            for _ in range(calls):
                rhs(v)
            best = min(best, (time.perf_counter() - start) / calls * 1e3)
    return best, first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", default="air3d", help="a registered system or module:Class")
    parser.add_argument("--grids", type=int, nargs="+", default=[51])
    parser.add_argument("--mode", choices=["eager", "compiled", "both"], default="both")
    parser.add_argument("--calls", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reuse-compile-cache", action="store_true")
    parser.add_argument("--quick", action="store_true", help="a smoke run: eager, 21 nodes, 2 calls")
    args = parser.parse_args()
    if args.quick:
        args.grids, args.mode, args.calls, args.repeats = [21], "eager", 2, 1
    if not args.reuse_compile_cache:
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="reach-inductor-")
    modes = ["eager", "compiled"] if args.mode == "both" else [args.mode]
    print(
        f"# {args.system}: one right-hand side, best mean of {args.repeats} x {args.calls} calls, "
        f"{torch.get_num_threads()} threads, torch {torch.__version__}"
    )
    print("| grid | mode | ms per call | first call s |")
    print("|---|---|---:|---:|")
    dims = make_system(args.system).state_dim
    for n in args.grids:
        for mode in modes:
            ms, first = time_rhs(args.system, n, mode == "compiled", args.calls, args.repeats)
            print(f"| {n}^{dims} | {mode} | {ms:.2f} | {first:.1f} |", flush=True)


if __name__ == "__main__":
    main()
