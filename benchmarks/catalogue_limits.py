"""What limits the catalogue's models (issue 42, point 4): the measurements behind docs/results/training.md.

Run: ``python benchmarks/catalogue_limits.py [--states 100000]`` (needs the recipes' run directories
in ``runs/catalogue`` for the loss columns; a missing run is named and skipped).

For each model of 6D and above it prints, side by side:

- the card's wrong-claim rate (false safe for avoid, false reachable for reach-avoid) against the
  goal of 0.05 %, and its delta-level volume (blank where no delta level certified);
- the training residual at the end of its recipe: the mean of each logged loss term over the last
  200 logged steps of ``runs/catalogue/NAME/metrics.jsonl``;
- the spread of the system's margins and of the shipped network's value ``V(x, T)`` on ``--states``
  uniform states: a network whose output scale (it starts near 1) is far from its margins', or
  whose value is the margin itself, has not learned the reachability;
- the share of the box the network calls safe (or the goal reachable), and for avoid models the
  share where it has learned anything beyond the failure margin (``V < l - 0.01``): the BRT grows
  out of the failure set only where the value falls below the margin.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from reach.systems import make_system
from safety.value_loading import load_value_function
from training import pretrained

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("multivehicle12d", "multivehicle15d", "narrowpassage", "quadrotor", "reachavoidrocketlanding")
GOAL = 5e-4


def residual(name: str, last: int = 200) -> dict[str, float] | None:
    """Mean of each loss term over the last ``last`` logged steps of the recipe's run (None: no run)."""
    path = ROOT / "runs" / "catalogue" / name / "metrics.jsonl"
    if not path.is_file():
        return None
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if "loss" in r][-last:]
    keys = [k for k in rows[-1] if k in ("loss", "pde", "upper_bound", "gradient")]
    return {k: sum(r.get(k, 0.0) for r in rows) / len(rows) for k in keys}


def spread(values: torch.Tensor) -> str:
    q = torch.quantile(values.double(), torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64))
    return f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--states", type=int, default=100_000)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    print(
        "| model | wrong claims % (goal 0.05) | delta-level vol. | loss / pde at the end | margins min / median / max "
        "| V(x, T) min / median / max | claimed safe or reachable % | V < l - 0.01 % |"
    )
    print("|---|---:|---:|---|---|---|---:|---:|")
    for name in NAMES:
        card = pretrained.card(name)
        metrics = card.evaluation["metrics"]
        wrong = metrics.get("false_safe_rate", metrics.get("false_reachable_rate"))
        volume = metrics.get("scenario_volume")
        system = make_system(card.system)
        vf = load_value_function(pretrained.PREFIX + name).value_function
        x = system.sample_states(args.states, generator=torch.Generator().manual_seed(args.seed))
        value = vf.value(x, torch.full((args.states,), float(system.horizon)))
        margins = [system.failure_margin(x)]
        if system.problem.reaches:
            margins.append(system.target_margin(x))
        claimed = system.problem.orient(value) > 0
        below = "" if system.problem.reaches else f"{100 * float((value < margins[0] - 0.01).float().mean()):.1f}"
        terms = residual(name)
        loss = "(no run)" if terms is None else " / ".join(f"{terms[k]:.4f}" for k in ("loss", "pde"))
        print(
            f"| {name} | {100 * wrong:.2f} ({wrong / GOAL:.0f}x) | {'-' if volume is None else f'{volume:.3f}'} | "
            f"{loss} | {'; '.join(spread(m) for m in margins)} | {spread(value)} | "
            f"{100 * float(claimed.float().mean()):.1f} | {below} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
