"""Why the vertical drone (``parameterizedvertdrone2d``) was learned wrong, scored against its exact solution.

Run::

    python benchmarks/vertdrone_domain.py --score pretrained:parameterizedvertdrone2d GRID.npz
    python benchmarks/vertdrone_domain.py --train-steps 1500 --out runs/vertdrone-box --threads 1

The drone's gain ``k`` has no dynamics, so each state is a 1D double integrator ``z'' = k u - g``
(``|u| <= 1``) that must keep ``z`` within [0, 3]. Its value ``V = max_u min_s l(z(s))`` is bracketed
without any grid or network:

* **above**: full thrust up (down) puts the drone at least as high (at most as high) at every time as
  any other input does, so ``V <= min(min_s z+(s), min_s 3 - z-(s))`` (closed form);
* **below**: the value any two-piece input achieves (``u`` in {-1, hover, +1} before and after a
  switch, switch times 0.02 s apart, heights checked every 0.005 s) is a lower bound.

Where the two meet (most of the box) the value is exact; the sign of ``V`` is known wherever the
lower bound is above zero or the upper one at or below it. Every value function given is scored on
the same uniform states of the box at ``t = 1``: its false safe and false unsafe shares against that
sign, the IoU of its BRT ``{V <= 0}`` with the exact one, its value MSE where the bracket is tight,
and where its false safe states lie: in the states whose best trajectory (full thrust up) leaves the
box through ``v = -4`` before it meets the floor, and on either side of hover thrust ``k = g``.

``--train-steps`` trains the default recipe (``reach train`` defaults, seed 0) twice for the same
number of steps: once drawing its points from the box itself (as the shipped model did) and once
from the system's ``training_domain()``, then scores both (``--variants`` picks one, and
``--value-scale`` sets the runs' output scale).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

GRAVITY = 9.8
HORIZON = 1.0


def uniform_box_states(n: int, seed: int) -> torch.Tensor:
    """``n`` states uniform on the drone's box ``v`` in [-4, 4], ``z`` in [-0.5, 3.5], ``k`` in [0, 12]."""
    from reach.systems import ParameterizedVertDrone2D  # lazy: heavy import after argument parsing

    box = torch.tensor(ParameterizedVertDrone2D().domain, dtype=torch.float64)
    r = torch.rand((n, 3), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return box[:, 0] + r * (box[:, 1] - box[:, 0])


def value_upper(v: torch.Tensor, z: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """``min(min_s z+(s), min_s 3 - z-(s))`` over ``s`` in [0, HORIZON], exactly (a quadratic's ends and vertex)."""
    bounds = []
    for accel, floor_side in ((k - GRAVITY, True), (-k - GRAVITY, False)):
        vertex = (-v / torch.where(accel.abs() < 1e-12, torch.full_like(accel, 1e-12), accel)).clamp(0.0, HORIZON)
        times = torch.stack([torch.zeros_like(v), torch.full_like(v, HORIZON), vertex])
        height = z + v * times + 0.5 * accel * times**2
        bounds.append((height if floor_side else 3.0 - height).min(0).values)
    return torch.minimum(bounds[0], bounds[1])


def value_lower(
    v: torch.Tensor, z: torch.Tensor, k: torch.Tensor, ds: float = 0.005, switch: float = 0.02
) -> torch.Tensor:
    """The best ``min_s l(z(s))`` over two-piece inputs: a lower bound of the value (each is an admissible input)."""
    hover = (GRAVITY / k.clamp_min(1e-9)).clamp(-1.0, 1.0)
    inputs = [-torch.ones_like(k), hover, torch.ones_like(k)]
    s = torch.arange(0.0, HORIZON + 1e-9, ds, dtype=v.dtype)[:, None]
    best = torch.full_like(v, -math.inf)
    for u1 in inputs:
        for u2 in inputs:
            a1, a2 = k * u1 - GRAVITY, k * u2 - GRAVITY
            for tau in torch.arange(0.0, HORIZON + 1e-9, switch, dtype=v.dtype).tolist():  # 51 switch times
                before, after = s.clamp(max=tau), (s - tau).clamp(min=0.0)
                height = z + v * before + 0.5 * a1 * before**2 + (v + a1 * before) * after + 0.5 * a2 * after**2
                best = torch.maximum(best, torch.minimum(height, 3.0 - height).min(0).values)
    return best


def leaves_through_floor_speed(v: torch.Tensor, z: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """States whose full-thrust-up trajectory (the best against the floor) passes ``v = -4`` within the
    horizon while still above the floor: their value is decided outside the box."""
    accel = k - GRAVITY
    falling = accel < 0
    t_exit = torch.where(falling, (v + 4.0) / (-accel).clamp_min(1e-12), torch.full_like(v, math.inf))
    height_at_exit = z + v * t_exit + 0.5 * accel * t_exit**2
    return falling & (t_exit <= HORIZON) & (z > 0) & (height_at_exit > 0)


def score(name: str, values: torch.Tensor, x: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> dict[str, float]:
    """One value function's row against the exact sign (``low > 0``: safe; ``high <= 0``: unsafe)."""
    k = x[:, 2]
    safe, claimed = low > 0, values > 0
    false_safe = claimed & ~safe
    brt, learned_brt = ~safe, ~claimed
    exact = (high - low).abs() < 1e-3
    outside = leaves_through_floor_speed(*x.unbind(-1))
    below_hover = k < GRAVITY
    return {
        "name": name,
        "false_safe": float(false_safe.double().mean()),
        "false_unsafe": float((~claimed & safe).double().mean()),
        "iou_brt": float((brt & learned_brt).sum() / (brt | learned_brt).sum()),
        "mse_exact": float(((values - low)[exact] ** 2).mean()),
        "lowest_fall": float((values - torch.minimum(x[:, 1], 3.0 - x[:, 1])).min()),  # min of V - l
        "false_safe_leaving_share": float(outside[false_safe].double().mean()) if false_safe.any() else 0.0,
        "false_safe_in_leaving": float(false_safe[outside].double().mean()),
        "false_safe_in_staying": float(false_safe[~outside].double().mean()),
        "false_safe_k_below_g": float(false_safe[below_hover].double().mean()),
        "false_safe_k_above_g": float(false_safe[~below_hover].double().mean()),
        "false_safe_near_hover": float(false_safe[(k - GRAVITY).abs() < 0.5].double().mean()),
    }


def print_rows(
    rows: list[dict[str, float]], n: int, seed: int, exact_share: float, leaving_share: float, lowest_exact_fall: float
) -> None:
    print(f"{n} uniform box states (seed {seed}) at t = {HORIZON}; value exact (bracket < 1e-3) on {exact_share:.4f}")
    print(f"share of the box whose best trajectory leaves through v = -4 above the floor: {leaving_share:.4f}")
    print(f"lowest V - l of the exact values: {lowest_exact_fall:.2f}")
    print(
        "| value function | false safe % | false unsafe % | BRT IoU | MSE (exact states) | false safe % of "
        "leaving states | of staying states | share of false safe that leave | k < g | k >= g | abs(k - g) < 0.5 "
        "| min V - l |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['name']} | {100 * r['false_safe']:.2f} | {100 * r['false_unsafe']:.2f} | {r['iou_brt']:.4f} | "
            f"{r['mse_exact']:.2e} | {100 * r['false_safe_in_leaving']:.2f} | {100 * r['false_safe_in_staying']:.2f} | "
            f"{r['false_safe_leaving_share']:.3f} | {100 * r['false_safe_k_below_g']:.2f} | "
            f"{100 * r['false_safe_k_above_g']:.2f} | {100 * r['false_safe_near_hover']:.2f} | {r['lowest_fall']:.2f} |"
        )


def train_pair(steps: int, out: Path, threads: int, variants: list[str], value_scale: float | None) -> list[str]:
    """Train the default recipe on the box and/or on ``training_domain()`` (``variants``), same seed,
    steps and ``value_scale``; the run dirs."""
    from reach.systems import ControlAffineSystem, ParameterizedVertDrone2D  # lazy: heavy imports
    from training.config import TrainConfig  # lazy: heavy imports
    from training.trainer import Trainer  # lazy: heavy imports

    torch.set_num_threads(threads)
    runs = []
    widened = ParameterizedVertDrone2D.training_domain
    for label in variants:
        run = out / label
        runs.append(str(run))
        if (run / "config.json").exists():
            print(f"{run}: exists, scored as it is")
            continue
        # the box run restores the default hook: points drawn from the domain, as before the fix
        ParameterizedVertDrone2D.training_domain = ControlAffineSystem.training_domain if label == "box" else widened
        try:
            config = TrainConfig(
                system="parameterizedvertdrone2d", steps=steps, seed=0, eval_every_s=1e9, value_scale=value_scale
            )
            summary = Trainer(config, run, progress=False).train()
        finally:
            ParameterizedVertDrone2D.training_domain = widened
        print(f"{run}: {summary.get('steps', steps)} steps in {summary.get('wall_time_s', float('nan')):.0f} s")
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--score", nargs="*", default=[], help="value functions to score (paths, pretrained:NAME, grids)"
    )
    parser.add_argument("--train-steps", type=int, default=0, help="also train the two recipes this many steps")
    parser.add_argument(
        "--out", type=Path, default=Path("runs/vertdrone-box"), help="where --train-steps writes its runs"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--variants", default="box,training-domain", help="which of box,training-domain to train")
    parser.add_argument(
        "--value-scale", type=float, default=None, help="the runs' value_scale (default: the system's own)"
    )
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    from safety.value_loading import load_value_function  # lazy: heavy import after argument parsing

    sources = list(args.score) + (
        train_pair(args.train_steps, args.out, args.threads, args.variants.split(","), args.value_scale)
        if args.train_steps
        else []
    )
    x = uniform_box_states(args.samples, args.seed)
    low, high = value_lower(*x.unbind(-1)), value_upper(*x.unbind(-1))
    rows = []
    for source in sources:
        vf = load_value_function(source).value_function
        with torch.no_grad():
            values = vf.value(x.float(), HORIZON).double()
        rows.append(score(source, values, x, low, high))
    exact_share = float(((high - low).abs() < 1e-3).double().mean())
    leaving = float(leaves_through_floor_speed(*x.unbind(-1)).double().mean())
    print(f"sign known on {float(((low > 0) | (high <= 0)).double().mean()):.4f} of the states")
    exact = (high - low).abs() < 1e-3
    lowest = float((low - torch.minimum(x[:, 1], 3.0 - x[:, 1]))[exact].min())
    print_rows(rows, args.samples, args.seed, exact_share, leaving, lowest)


if __name__ == "__main__":
    main()
