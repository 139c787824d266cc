"""A reach-avoid car written as a user writes one, trained for ten CPU minutes (issue 63, point 3).

The defaults must carry to systems they were not tuned on. :class:`WindyCar` below is defined the way
the tutorial teaches (docs/custom_system.md, section 9): states, domain, input boxes, dynamics and the
two margins, nothing else (no ``target_floor``, no ``value_scale``; ``margin_rate_bound`` as the
tutorial's cars declare it). Its goal, obstacle, speeds and box differ from the built-in
``dubinsreachavoid``, on which the defaults were measured. The goal: volume IoU >= 0.97 against the
101^3 grid at the horizon, from ten minutes of ``reach train`` on the 2-core machine.

Run on a quiet machine (the budget is wall time)::

    python benchmarks/user_car_ten_minutes.py --budget 10m --out runs/user-car
    python benchmarks/user_car_ten_minutes.py --budget 10m --recipe points=2048 --out runs/user-car

Each recipe is ``reach train --system user_car_ten_minutes:WindyCar --budget B --seed S`` plus its
``--recipe FIELD=VALUE`` settings (``training.TrainConfig`` fields), scored on every node of the 101^3
grid at the horizon (solved into ``--gt`` when missing): volume IoU of the reach-avoid set and value
MSE. ``--steps N`` trains a fixed number of steps instead of a budget (to compare recipes by step
count on a busy machine; their time per step is then measured separately). A finished run is scored
again, not retrained, when the command is repeated.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))  # so that ``user_car_ten_minutes:WindyCar`` imports in reach's own process
sys.path.insert(0, str(HERE.parent / "examples"))  # the tutorial's ``my_systems:DubinsGap``

from reach.systems import Box, ControlAffineSystem  # noqa: E402
from reach_cli import main as reach_main  # noqa: E402
from reach_cli.sweep import parse_train_options  # noqa: E402
from reach_cli.train import train_flags  # noqa: E402

GOAL_IOU = 0.97
SYSTEM = "user_car_ten_minutes:WindyCar"


class WindyCar(ControlAffineSystem):
    """A Dubins car that must reach a goal disc within 2 s, past one round obstacle, against a wind of
    up to 0.1 per axis; written as in the tutorial, with its own geometry."""

    name = "windy-car"
    kind = "reach-avoid"
    state_names = ("px", "py", "heading")
    periodic = (False, False, True)

    def __init__(
        self,
        speed: float = 0.5,
        max_turn_rate: float = 1.2,
        wind: float = 0.1,
        goal: tuple[float, float] = (0.8, 0.3),
        goal_radius: float = 0.25,
        obstacle: tuple[float, float] = (0.2, 0.1),
        obstacle_radius: float = 0.3,
        horizon: float = 2.0,
    ) -> None:
        self.speed, self.max_turn_rate, self.wind = speed, max_turn_rate, wind
        self.goal, self.goal_radius = tuple(goal), goal_radius
        self.obstacle, self.obstacle_radius, self.horizon = tuple(obstacle), obstacle_radius, horizon
        self.domain = ((-1.2, 1.2), (-1.2, 1.2), (-math.pi, math.pi))
        self.control_bounds = Box.symmetric([max_turn_rate])
        self.disturbance_bounds = Box.symmetric([wind, wind])

    def parameters(self) -> dict:
        return {
            "speed": self.speed,
            "max_turn_rate": self.max_turn_rate,
            "wind": self.wind,
            "goal": list(self.goal),
            "goal_radius": self.goal_radius,
            "obstacle": list(self.obstacle),
            "obstacle_radius": self.obstacle_radius,
            "horizon": self.horizon,
        }

    def drift(self, x, xp):
        return [self.speed * xp.cos(x[2]), self.speed * xp.sin(x[2]), 0.0 * x[2]]

    def control_matrix(self, x, xp):
        return {(2, 0): 1.0}

    def disturbance_matrix(self, x, xp):
        return {(0, 0): 1.0, (1, 1): 1.0}

    def target_margin_columns(self, x, xp):
        """Negative inside the goal disc."""
        return xp.hypot(x[0] - self.goal[0], x[1] - self.goal[1]) - self.goal_radius

    def constraint_margin_columns(self, x, xp):
        """Positive away from the obstacle disc."""
        return xp.hypot(x[0] - self.obstacle[0], x[1] - self.obstacle[1]) - self.obstacle_radius

    def margin_rate_bound(self) -> float:
        return self.speed + math.sqrt(2.0) * self.wind


def _score(run: Path, gt: Path) -> dict:
    from groundtruth import GridSolution
    from training import NeuralValueFunction, load_network
    from training.accuracy import ReferenceEvaluator

    grid = GridSolution.load(gt, outside="clamp")
    evaluator = ReferenceEvaluator(grid, float(grid.times[-1]))  # the horizon
    return evaluator(NeuralValueFunction(load_network(run / "checkpoint.pt")))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budget", default="10m")
    parser.add_argument("--steps", type=int, default=None, help="train this many steps instead of --budget")
    parser.add_argument(
        "--system",
        default=SYSTEM,
        help=f"the car (default {SYSTEM}; also my_systems:DubinsGap, or a built-in's name)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--recipe", nargs="*", default=[], metavar="FIELD=VALUE")
    parser.add_argument("--gt", default="runs/user-car/gt101.npz", help="ground-truth cache (101^3)")
    parser.add_argument("--out", required=True, help="the run's folder")
    args = parser.parse_args()
    try:
        fields = parse_train_options(args.recipe, "--recipe")
    except ValueError as err:
        raise SystemExit(str(err)) from err
    # a system named by a file is imported only when named on purpose: the grid and the checkpoint name it too
    if ":" in args.system:
        importlib.import_module(args.system.partition(":")[0])
    gt, run = Path(args.gt), Path(args.out)
    if not gt.exists():
        gt.parent.mkdir(parents=True, exist_ok=True)
        solve = ["--threads", str(args.threads), "groundtruth", args.system, "--grid", "101", "--out", str(gt)]
        code = reach_main(solve)
        if code:
            return code
    if not (run / "checkpoint.pt").exists():
        stop = ["--steps", str(args.steps)] if args.steps else ["--budget", args.budget]
        command = ["--threads", str(args.threads), "train", "--system", args.system, *stop, "--seed", str(args.seed)]
        command += [*train_flags(fields), "--out", str(run)]
        print("reach " + " ".join(command), flush=True)
        if reach_main(command):
            return 1
    meta = json.loads((run / "checkpoint.json").read_text())
    metrics = _score(run, gt)
    result = {"recipe": fields, "seed": args.seed, "steps": meta["steps"], "wall_s": meta["wall_time_s"], **metrics}
    (run / "score.json").write_text(json.dumps(result, indent=1))
    print(
        f"{run}: {result['steps']} steps in {result['wall_s']:.0f} s, volume IoU {result['iou_volume']:.4f} "
        f"(goal {GOAL_IOU}), volume MSE {result['mse_volume']:.2e}, slice IoU {result['iou_slice']:.4f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
