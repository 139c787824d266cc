"""State limits that a system's inputs respect, kept by the discrete step as the continuous system keeps them.

Some systems bound their inputs by the state: NarrowPassage's acceleration may not push a car's
speed above 6.5 or below 0.001, nor its steering rate the steering angle past its stop (the input
bound on that side is 0 at the limit, as in DeepReach). In continuous time each limit is then
forward invariant: a state that starts on its inside stays there, and one that starts outside can
only move toward it. A fixed step holds the input over the whole step, so it overshoots the limit
(full throttle from 6.49 for 0.01 s gives 6.51). A system declares its limits
(:meth:`StateLimits.state_limits`) and the one stepper (:func:`reach.integrators.make_stepper`)
saturates each step (:meth:`StateLimits.saturate_columns`), on every backend: envs, rollouts,
filters and the verifier's interval boxes alike.

Why a module of its own: a declaration and its one generic use, apart from the physics declarations
of :class:`~reach.systems.base.ControlAffineSystem`, which inherits :class:`StateLimits`. A system
that declares none (the default) steps exactly as its dynamics say, with no extra work.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from reach.systems.arrays import Backend, Column


class StateLimits:
    """Bounds on state dimensions that a :class:`~reach.systems.base.ControlAffineSystem`'s inputs
    respect; a system that has such bounds overrides :meth:`state_limits`."""

    def state_limits(self) -> Mapping[int, tuple[float, float]]:
        """``{dimension: (low, high)}``: the limits the inputs keep each listed (non-periodic) dimension
        within, each side forward invariant in continuous time. Empty by default: no limits."""
        return {}

    def saturate_columns(self, before: Sequence[Column], after: Sequence[Column], xp: Backend) -> list[Column]:
        """``after`` (one step from ``before``) with each limited dimension kept on the inside of each
        of its limits that it started on: clamped back to ``high`` if it started at or below ``high``,
        to ``low`` if it started at or above ``low``; a side it started outside of is left as the
        dynamics move it (toward the limit). NaN stays NaN, for the callers' finiteness checks."""
        out = list(after)
        for i, (low, high) in self.state_limits().items():
            value = xp.where(before[i] >= low, xp.clip(out[i], low, math.inf), out[i])
            out[i] = xp.where(before[i] <= high, xp.clip(value, -math.inf, high), value)
        return out

    def check_state_limits(self, what: str) -> None:
        """Refuse, naming it, a limit on a dimension that is not a state's, or is periodic, or whose
        bounds are not finite with ``low < high`` (run on construction)."""
        limits = self.state_limits()
        if not isinstance(limits, Mapping):
            raise ValueError(f"{what}: state_limits must return a mapping {{dimension: (low, high)}}, got {limits!r}")
        names, periodic = self.state_names, self.periodic
        for i, bounds in limits.items():
            if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < len(names) or periodic[i]:
                raise ValueError(f"{what}: state_limits key {i!r} must index a non-periodic state dimension")
            ok = isinstance(bounds, tuple) and len(bounds) == 2 and all(isinstance(b, (int, float)) for b in bounds)
            if not (ok and math.isfinite(bounds[0]) and math.isfinite(bounds[1]) and bounds[0] < bounds[1]):
                rule = "finite (low, high) with low < high"
                raise ValueError(f"{what}: state_limits of {names[i]} must be {rule}, got {bounds!r}")


__all__ = ["StateLimits"]
