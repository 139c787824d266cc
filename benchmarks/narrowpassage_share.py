"""How much of NarrowPassage's box could ever succeed: an upper bound from how far the cars can move.

Run::

    python benchmarks/narrowpassage_share.py [--samples 1000000] [--horizons 1,2,4,8] [--seed 0]

On uniform states of the box (the cards' sampling), the shares that start in violation of the
constraint (a collision, with a curb, the stranded car or each other: ``g <= 0``), that start in the
target, and that could reach the target within each horizon without starting in violation: the
target floor (:meth:`~reach.systems.deepreach_catalogue.NarrowPassage.target_floor`, each car moving
at most ``|v| t + t^2``) is not positive. The last is an upper bound of the reach-avoid set's share
(a state must also stay out of collision on the way, and turn to its goal); a policy's successful
rollouts give a lower bound (``1 - failure_rate`` on a card). Prints one row per horizon.
"""

from __future__ import annotations

import argparse
import sys

import torch

from reach.systems.deepreach_catalogue import NarrowPassage
from reach.validation import csv_floats, positive_finite, positive_int_arg, seed_arg
from safety.verification.verify import sample_states


def shares(samples: int, horizons: list[float], seed: int, chunk: int = 200_000) -> list[dict[str, float]]:
    """Per horizon: the shares of ``samples`` uniform states that start in violation, start in the
    target, and could reach it in time (the upper bound), in chunks of ``chunk`` states."""
    system = NarrowPassage()
    states = sample_states(system, samples, seed)
    violation = started = 0
    within = [0] * len(horizons)
    for lo in range(0, samples, chunk):
        x = states[lo : lo + chunk].to(torch.float64)
        valid = system.failure_margin(x) > 0
        violation += int((~valid).sum())
        started += int((valid & (system.target_margin(x) <= 0)).sum())
        for k, horizon in enumerate(horizons):
            within[k] += int((valid & (system.target_floor(x, horizon) <= 0)).sum())
    return [
        {
            "horizon": h,
            "violation_at_start": violation / samples,
            "target_at_start": started / samples,
            "goal_within_reach": w / samples,
        }
        for h, w in zip(horizons, within)
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=positive_int_arg, default=1_000_000)
    parser.add_argument("--horizons", default="1,2,4,8", help="comma-separated horizons in seconds")
    parser.add_argument("--seed", type=seed_arg, default=0)
    args = parser.parse_args(argv)
    try:
        horizons = csv_floats("--horizons", args.horizons, positive_finite)
    except ValueError as err:
        parser.error(str(err))
    print(f"NarrowPassage, {args.samples:,} uniform states of the box (seed {args.seed})")
    print("| horizon (s) | start in violation % | start in the target % | goal within reach, no violation at start % |")
    print("|---:|---:|---:|---:|")
    for row in shares(args.samples, horizons, args.seed):
        print(
            f"| {row['horizon']:g} | {100 * row['violation_at_start']:.2f} | {100 * row['target_at_start']:.3f} "
            f"| {100 * row['goal_within_reach']:.2f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
