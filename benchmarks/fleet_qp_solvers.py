"""The fleet filter's QP, solved by Clarabel (interior point) and by OSQP (ADMM) on the same saved problems.

Run: ``python benchmarks/fleet_qp_solvers.py [--problems runs/fleet_qp_problems.npz] [--repeats 20]``
(needs ``pip install osqp``; Clarabel is a dependency of reach).

What it does:

1. Saves the problems (unless ``--problems`` exists): the stacked QPs
   (:class:`safety.fleet.qp.ConflictQP`) that :class:`safety.fleet.FleetFilter` builds on random
   fleets (16 and 64 cars, random positions at about one car per 1.6 m^2, random headings; a batch
   of 1 and of 64 states; ``gamma`` 1 and 0.2), recorded as the filter hands them to its solver.
2. Solves each problem with Clarabel (as the filter does: one thread, default tolerances), OSQP at
   its defaults (``eps_abs = eps_rel = 1e-3``) and OSQP tightened (``1e-6``, polished).
3. Prints per solver: the median and worst time per solve (``time.perf_counter`` around the solver's
   setup and solve, on one thread, the median of ``--repeats`` solves per problem), the worst
   violation of the softened problem's constraints by the returned point (rows unit-scaled:
   ``c . w + s >= rhs``, ``s >= 0``, ``|w| <= bound``), the worst violation of the hard conditions
   ``c . w >= rhs`` on the conflicts Clarabel finds feasible (slack <= 1e-6), and the worst
   objective above Clarabel's.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from groundtruth.solution import GridSolution
from reach.systems import MultiVehicle
from reach.systems.multivehicle import Car
from safety.fleet import FleetFilter, FleetFilterSettings, FleetValue
from safety.fleet import filter as fleet_filter
from safety.fleet.qp import ConflictQP
from safety.fleet.qp import solve as clarabel_solve

FIELDS = ("nominal", "bound", "columns", "coefficients", "rhs")


def record_problems(seed: int = 0) -> list[ConflictQP]:
    """The QPs the fleet filter builds on random fleets (module docstring)."""
    pair = GridSolution.load("training/pretrained/relativepair.npz", outside="clamp")
    seen: list[ConflictQP] = []
    real = fleet_filter.solve

    def spy(qp: ConflictQP):
        seen.append(qp)
        return real(qp)

    fleet_filter.solve = spy
    g = torch.Generator().manual_seed(seed)
    try:
        for n in (16, 64):
            side = math.sqrt(1.6 * n)
            fv = FleetValue(MultiVehicle([Car(0.6, 1.1)] * n, half_width=side), pair)
            for gamma in (1.0, 0.2):
                ff = FleetFilter(fv, FleetFilterSettings(dt=0.05, gamma=gamma))
                for batch, calls in ((1, 30), (64, 3)):
                    for _ in range(calls):
                        pos = torch.rand(batch, 2 * n, generator=g, dtype=torch.float64) * side
                        th = (torch.rand(batch, n, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
                        u = (torch.rand(batch, n, generator=g, dtype=torch.float64) * 2 - 1) * 1.1
                        ff(torch.cat([pos, th], 1), 1.0, u)
    finally:
        fleet_filter.solve = real
    return seen


def save(problems: list[ConflictQP], path: Path) -> None:
    arrays = {f"{k}_{f}": getattr(qp, f) for k, qp in enumerate(problems) for f in FIELDS}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, count=len(problems), penalty=problems[0].penalty, **arrays)


def load(path: Path) -> list[ConflictQP]:
    with np.load(path) as data:
        return [
            ConflictQP(*(data[f"{k}_{f}"] for f in FIELDS), float(data["penalty"])) for k in range(int(data["count"]))
        ]


def solve_osqp(qp: ConflictQP, tight: bool) -> np.ndarray:
    import osqp  # lazy: a benchmark-only dependency

    p, q, a, b = qp.matrices()
    prob = osqp.OSQP()
    options = {"eps_abs": 1e-6, "eps_rel": 1e-6, "polishing": True, "max_iter": 100_000} if tight else {}
    prob.setup(p.tocsc(), q, a.tocsc(), np.full(a.shape[0], -np.inf), b, verbose=False, **options)
    return np.asarray(prob.solve().x, dtype=np.float64)


def solve_clarabel(qp: ConflictQP) -> np.ndarray:
    import clarabel  # lazy: as safety.fleet.qp imports it

    p, q, a, b = qp.matrices()
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.max_threads = 1
    return np.asarray(clarabel.DefaultSolver(p, q, a, b, [clarabel.NonnegativeConeT(a.shape[0])], settings).solve().x)


def objective(qp: ConflictQP, w: np.ndarray, s: np.ndarray) -> float:
    """The QP's objective (without its constant): distance to the nominal plus the slacks' price."""
    return float(((w - qp.nominal) ** 2).sum() + qp.penalty * s.sum())


def measure(problems: list[ConflictQP], repeats: int) -> None:
    solvers = {
        "clarabel": solve_clarabel,
        "osqp (defaults)": lambda qp: solve_osqp(qp, False),
        "osqp (1e-6, polished)": lambda qp: solve_osqp(qp, True),
    }
    reference = [clarabel_solve(qp) for qp in problems]
    sizes = [qp.sizes for qp in problems]
    print(
        f"{len(problems)} problems: variables {min(s[0] for s in sizes)}-{max(s[0] for s in sizes)}, "
        f"conditions {min(s[1] for s in sizes)}-{max(s[1] for s in sizes)}"
    )
    print(
        "| solver | median ms | worst ms | worst soft-constraint violation | worst hard violation (feasible) "
        "| worst objective excess |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for name, fn in solvers.items():
        times, soft, hard, excess = [], 0.0, 0.0, 0.0
        for qp, ref in zip(problems, reference):
            per = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                z = fn(qp)
                per.append(time.perf_counter() - t0)
            times.append(statistics.median(per))
            nv = qp.sizes[0]
            w, s = z[:nv], z[nv:]
            coef, rhs = qp.scaled()
            cols = np.where(qp.columns >= 0, qp.columns, 0)
            lhs = (np.where(qp.columns >= 0, coef, 0.0) * w[cols]).sum(1)
            soft = max(soft, float(np.max(np.r_[rhs - lhs - s, -s, np.abs(w) - qp.bound, 0.0])))
            feasible = ref.slack <= 1e-6
            hard = max(hard, float(np.max(np.r_[(rhs - lhs)[feasible], 0.0])))
            excess = max(excess, objective(qp, w, s) - objective(qp, ref.w, ref.slack))
        ms = f"{1e3 * statistics.median(times):.3f} | {1e3 * max(times):.3f}"
        print(f"| {name} | {ms} | {soft:.1e} | {hard:.1e} | {excess:.1e} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=Path, default=Path("runs/fleet_qp_problems.npz"))
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if not args.problems.exists():
        save(record_problems(), args.problems)
    measure(load(args.problems), args.repeats)


if __name__ == "__main__":
    main()
