"""The reach rocket's exact reach set, and which of a network's wrong claims are value errors and which policy errors.

``rocketlanding`` (DeepReach's RocketLanding, 6D reach) needs no grid to be solved. Its thrust ``u``
lies in a disc of radius ``A = 250`` in the body frame, and turning by the heading maps that disc onto
itself, so the world-frame acceleration is any vector of the same disc whatever ``th`` and ``w`` do;
gravity adds ``(0, -g)``. The positions reachable at time ``t`` from ``(p, v)`` are then exactly the
disc of centre ``p + v t + (0, -g) t^2 / 2`` and radius ``A t^2 / 2`` (a double integral of a
disc-bounded input; its rim is reached by a constant thrust direction). A state can reach the
landing zone ``|x| <= 20, y <= 20`` within the horizon exactly when, at some ``t`` in ``[0, T]``,
that disc meets the zone, which this script checks on ``--time-steps`` times.

For every value function given it rolls out the same ``--samples`` uniform states (``--seed 0``: the
model card's) under the value's own policy with the cards' protocol, and splits its wrong claims
(claimed reachable, the rollout missed) into **value errors** (the state cannot reach the zone: the
claim itself is wrong) and **policy errors** (it can: the value's gradient policy failed to). It
also prints the claims' sign errors against the exact set both ways, and checks the exact set
against the rollouts (a rollout that reached the zone from outside the exact set would be a bug)::

    python benchmarks/rocket_exact_reach.py pretrained:rocketlanding --samples 20000
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import torch  # noqa: E402

from reach.systems import RocketLanding  # noqa: E402
from reach.validation import positive_int_arg  # noqa: E402


def exactly_reachable(system: RocketLanding, x: torch.Tensor, time_steps: int = 4000) -> torch.Tensor:
    """Per state ``(N, 6)``, whether some input reaches the landing zone within the horizon (checked at
    ``time_steps + 1`` times in ``[0, T]``): the reachable disc of positions meets the zone."""
    x = x.double()
    t = torch.linspace(0.0, system.horizon, time_steps + 1, dtype=torch.float64)[:, None]
    centre_x = x[:, 0] + x[:, 3] * t
    centre_y = x[:, 1] + x[:, 4] * t - 0.5 * system.gravity * t**2
    radius = 0.5 * system.thrust * t**2
    gap = torch.hypot(
        (centre_x.abs() - system.landing_half_width).clamp_min(0.0), (centre_y - system.landing_height).clamp_min(0.0)
    )
    return (gap <= radius).any(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sources", nargs="+", help="value functions of rocketlanding (run dirs, pretrained:NAME)")
    parser.add_argument("--samples", type=positive_int_arg, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--time-steps", type=positive_int_arg, default=4000)
    parser.add_argument("--threads", type=positive_int_arg, default=2)
    args = parser.parse_args()
    from safety.value_loading import load_value_function  # lazy: heavy imports after parsing
    from safety.verification.rollout import rollout
    from safety.verification.verify import sample_states

    torch.set_num_threads(args.threads)
    system = RocketLanding()
    value_functions = []  # every source loaded and checked before any rollout
    for source in args.sources:
        try:
            value_functions.append((source, load_value_function(source, system=system).value_function))
        except ValueError as error:
            raise SystemExit(f"rocket_exact_reach: {error}") from None
    x = sample_states(system, args.samples, args.seed)
    truth = exactly_reachable(system, x, args.time_steps)
    reachable = 100 * float(truth.double().mean())
    print(f"{args.samples} uniform states (seed {args.seed}); exactly reachable: {reachable:.3f} %")
    print(
        "| value function | claims % | wrong claims % (rollout) | ... value errors % | ... policy errors % "
        "| unclaimed, reachable % | rollouts reaching from outside the exact set |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for source, vf in value_functions:
        result = rollout(vf, x, progress=False)
        claims = result.oriented_value > 0
        wrong = claims & result.failed
        share = lambda mask: f"{100 * float(mask.double().mean()):.3f}"  # noqa: E731
        print(
            f"| {source} | {share(claims)} | {share(wrong)} | {share(wrong & ~truth)} | {share(wrong & truth)} | "
            f"{share(~claims & truth)} | {int((~result.failed & ~truth).sum())} |"
        )


if __name__ == "__main__":
    main()
