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

    python benchmarks/rocket_exact_reach.py exact pretrained:rocketlanding --samples 20000

``exact`` names :class:`ExactRocketValue`, the value function in closed form, as a source of its own:
its row is what an accurate value scores under the same protocol (its claims are the exact set's,
so its wrong claims are the protocol's policy errors; a value claiming less can score fewer).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import torch  # noqa: E402

from reach.systems import RocketLanding  # noqa: E402
from reach.validation import positive_float_arg, positive_int_arg  # noqa: E402
from reach.value_function import check_time  # noqa: E402


def reachable_disc(
    system: RocketLanding, x: torch.Tensor, s: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The disc of positions reachable from states ``x`` ``(..., 6)`` after times ``s`` (broadcast
    against the batch): its centre's ``x`` and ``y`` (the unthrusted fall) and its radius."""
    centre_x = x[..., 0] + x[..., 3] * s
    centre_y = x[..., 1] + x[..., 4] * s - 0.5 * system.gravity * s**2
    return centre_x, centre_y, 0.5 * system.thrust * s**2


def exactly_reachable(system: RocketLanding, x: torch.Tensor, time_steps: int = 4000) -> torch.Tensor:
    """Per state ``(N, 6)``, whether some input reaches the landing zone within the horizon (checked at
    ``time_steps + 1`` times in ``[0, T]``): the reachable disc of positions meets the zone."""
    x = x.double()
    t = torch.linspace(0.0, system.horizon, time_steps + 1, dtype=torch.float64)[:, None]
    centre_x, centre_y, radius = reachable_disc(system, x, t)
    gap = torch.hypot(
        (centre_x.abs() - system.landing_half_width).clamp_min(0.0), (centre_y - system.landing_height).clamp_min(0.0)
    )
    return (gap <= radius).any(0)


def disc_box_margin(a: torch.Tensor, b: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
    """The least ``m = max(|x| - 20, y - 20)`` over a disc of positions, given ``a = |cx| - 20`` and
    ``b = cy - 20`` of its centre and its ``radius``: the least ``k`` whose box ``{|x| <= 20 + k,
    y <= 20 + k}`` the disc meets, i.e. ``hypot((a - k)+, (b - k)+) = radius``. One side binds when
    ``|a - b| >= radius`` (``k = max(a, b) - radius``), else both (the quadratic's lower root). The
    margin is never below -20 (``|x| - 20`` at ``x = 0``), where the boxes start."""
    one_side = (a - b).abs() >= radius
    # the root only where both sides bind: elsewhere its argument may be <= 0, whose sqrt has no finite
    # gradient, and torch.where passes a NaN gradient of the branch it drops
    root = torch.sqrt(torch.where(one_side, torch.ones_like(radius), 2 * radius**2 - (a - b) ** 2))
    both = 0.5 * ((a + b) - root)
    return torch.where(one_side, torch.maximum(a, b) - radius, both).clamp_min(-20.0)


class ExactRocketValue:
    """The reach rocket's value function in closed form, a :class:`~reach.value_function.ValueFunction`.

    ``V(x, t) = min over s in [0, t] of l*(s)``, where ``l*(s)`` is the least target margin over the
    disc of positions reachable at ``s`` (:func:`disc_box_margin`, then the card's scaling: ``/150``
    outside the zone, ``/10`` inside). The minimum over inputs and the one over times commute, and
    each disc point is reached by a constant world-frame thrust, so this is the reach value itself,
    up to the minimum over ``s`` being taken on ``time_steps + 1`` times from 0 to ``t``. Its
    gradient (autograd through the minimum: the envelope theorem) is zero in ``th`` and ``w``; the
    system's ``u*`` then thrusts along ``-dV/dv``, turned into the body frame."""

    def __init__(self, system: RocketLanding, time_steps: int = 400) -> None:
        self.system = system
        self.time_steps = time_steps
        self.time_range = (0.0, float(system.horizon))

    def value(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        system = self.system
        check_time(t, *self.time_range)  # as a network refuses times it was not trained on
        t = torch.as_tensor(t, dtype=x.dtype, device=x.device).expand(x.shape[:-1])
        s = t[..., None] * torch.linspace(0.0, 1.0, self.time_steps + 1, dtype=x.dtype, device=x.device)
        centre_x, centre_y, radius = reachable_disc(system, x[..., None, :], s)
        m = disc_box_margin(centre_x.abs() - system.landing_half_width, centre_y - system.landing_height, radius).amin(
            -1
        )
        return torch.where(m >= 0, m / 150.0, m / 10.0)

    def value_and_gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.enable_grad():
            y = x.detach().requires_grad_(True)
            v = self.value(y, t)
            (g,) = torch.autograd.grad(v.sum(), y)
        return v.detach(), g

    def gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        return self.value_and_gradient(x, t)[1]


def closest_approach(system: RocketLanding, result: object) -> torch.Tensor:
    """Per recorded rollout, the least unscaled target margin ``max(|x| - 20, y - 20)`` along it (m):
    how far a failed rollout stayed from the zone. A rollout keeps its last state once decided; steps
    where a state is not finite (a NaN from the value's gradient) are skipped."""
    states = result.trajectories.double()  # (steps + 1, N, 6)
    margin = torch.maximum(states[..., 0].abs() - system.landing_half_width, states[..., 1] - system.landing_height)
    return torch.nan_to_num(margin, nan=math.inf).amin(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sources",
        nargs="*",
        help="value functions of rocketlanding (run dirs, pretrained:NAME); 'exact': ExactRocketValue",
    )
    parser.add_argument("--samples", type=positive_int_arg, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--time-steps", type=positive_int_arg, default=4000)
    parser.add_argument(
        "--value-times", type=positive_int_arg, default=400, help="times in [0, t] the closed form minimises over"
    )
    parser.add_argument(
        "--dt",
        type=positive_float_arg,
        default=None,
        help="the rollouts' step (default: the cards' protocol, 0.0025 s)",
    )
    parser.add_argument("--threads", type=positive_int_arg, default=2)
    args = parser.parse_args()
    if not args.sources:
        parser.error("name at least one value function (a run, pretrained:NAME, or exact)")
    from safety.value_loading import load_value_function  # lazy: heavy imports after parsing
    from safety.verification.rollout import rollout
    from safety.verification.verify import sample_states

    torch.set_num_threads(args.threads)
    system = RocketLanding()
    value_functions = []  # every source loaded and checked before any rollout
    for source in args.sources:
        if source == "exact":
            value_functions.append(
                (f"exact (closed form, {args.value_times} times)", ExactRocketValue(system, args.value_times))
            )
            continue
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
    step = {} if args.dt is None else {"dt": args.dt}
    misses = []
    for source, vf in value_functions:
        result = rollout(vf, x, progress=False, **step)
        claims = result.oriented_value > 0
        wrong = claims & result.failed
        share = lambda mask: f"{100 * float(mask.double().mean()):.3f}"  # noqa: E731
        print(
            f"| {source} | {share(claims)} | {share(wrong)} | {share(wrong & ~truth)} | {share(wrong & truth)} | "
            f"{share(~claims & truth)} | {int((~result.failed & ~truth).sum())} |"
        )
        if bool(wrong.any()):  # again, recorded: how close the failed rollouts came
            recorded = rollout(vf, x[wrong][:100_000], record=True, progress=False, **step)
            misses.append((source, closest_approach(system, recorded)))
    for source, miss in misses:
        near = int((miss <= 1).sum())
        print(
            f"{source}: its {len(miss)} wrong claims' closest approach to the zone (m, unscaled margin): "
            f"median {float(miss.median()):.3g}, largest {float(miss.max()):.3g}; within 1 m: {near}"
        )


if __name__ == "__main__":
    main()
