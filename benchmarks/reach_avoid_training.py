"""Which output parameterisation trains the reach-avoid car best: the measurement behind the default.

Run: ``python benchmarks/reach_avoid_training.py`` (``--steps 4000``, ``--budget 600`` for a
wall-clock budget per variant instead, ``--variants exact,exact-constraint,vanilla``).

Trains ``reach.systems.DubinsReachAvoid`` once per output parameterisation, everything else at the
library's defaults (the Air3D recipe: ``ssssl``, width 128, 8192 points a step, cosine schedule,
compiled fused residual), and scores each against a 101^3 grid solution at T = 2 s (solved here
once, or ``--groundtruth PATH``): the volume IoU of ``{V <= 0}`` and the value MSE, over every grid
node and over the reference slice.

- ``exact``: ``V = max(l, -g) + (t / T) o``: the boundary condition holds by construction, the
  constraint ``V >= -g`` only through the residual's ``min(., V + g)`` term;
- ``exact-constraint``: ``V = max(max(l, -g) + (t / T) o, -g)``: both hold by construction;
- ``vanilla``: DeepReach's ``V = o`` with a boundary loss at ``t = 0``.

It prints one row per variant (steps, wall time, IoU, MSE) and writes them to
``runs/kinds/reach_avoid_training.json``. Time it alone: a 2-core machine shared with other work
gives fewer steps per budget.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from groundtruth import GridSolution, solve
from reach.systems import DubinsReachAvoid
from training import TrainConfig, Trainer
from training.accuracy import ReferenceEvaluator
from training.checkpoint import load_network
from training.network import NeuralValueFunction

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=None, help="steps per variant (default: a 600 s budget)")
    parser.add_argument("--budget", type=float, default=None, help="wall-clock seconds per variant")
    parser.add_argument("--variants", default="exact,exact-constraint,vanilla")
    parser.add_argument("--groundtruth", default=None, help="a 101^3 DubinsReachAvoid solution (.npz)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(ROOT / "runs" / "kinds" / "parameterisations"))
    args = parser.parse_args()
    if args.steps is None and args.budget is None:
        args.budget = 600.0
    system = DubinsReachAvoid()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.groundtruth is None:
        start = time.perf_counter()
        grid = solve(system, 101, [0.1 * k for k in range(21)], progress=False)
        grid.save(out / "dra_101.npz")
        print(f"grid 101^3 to T = 2 s: {time.perf_counter() - start:.1f} s")
    else:
        grid = GridSolution.load(args.groundtruth)
    evaluator = ReferenceEvaluator(grid, 2.0)
    rows = []
    for variant in args.variants.split(","):
        config = TrainConfig(
            system=system, parameterisation=variant, steps=args.steps, budget_s=args.budget, seed=args.seed
        ).validate()
        run = out / variant
        summary = Trainer(config, run, progress=False).train()
        scores = evaluator(NeuralValueFunction(load_network(run / "checkpoint.pt")))
        row = {"parameterisation": variant, "steps": summary["steps"], "wall_s": summary["wall_time_s"], **scores}
        rows.append(row)
        print(
            f"{variant:>17}: {row['steps']} steps in {row['wall_s']:.0f} s, IoU vol. {row['iou_volume']:.4f}, "
            f"MSE vol. {row['mse_volume']:.2e}, IoU slice {row['iou_slice']:.4f}",
            flush=True,
        )
    path = ROOT / "runs" / "kinds" / "reach_avoid_training.json"
    path.write_text(
        json.dumps({"seed": args.seed, "steps": args.steps, "budget_s": args.budget, "rows": rows}, indent=2)
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
