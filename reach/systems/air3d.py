"""Two Dubins cars in the first car's frame: Air3D and the cooperative pair of the 9D system.

State ``x = (x1, x2, x3)``: car 2's position and heading relative to car 1, in car 1's frame::

    x1' = -v1 + v2 cos x3 + w1 x2
    x2' =        v2 sin x3 - w1 x1
    x3' = w2 - w1

``w1`` (car 1's turn rate) is a control. ``w2`` is a disturbance in Air3D (the pursuer attacks) and a
second control in the cooperative pair (both cars try to avoid each other, as in the 9D system).
Failure: the cars within ``collision_radius``, ``l(x) = ||(x1, x2)|| - R``.

:class:`RelativePair` holds the physics once; :class:`Air3D` is its adversarial instance with
DeepReach's constants and names (Mitchell et al. 2005; DeepReach).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, ClassVar

from reach.systems.arrays import Backend, Column, InputMatrix
from reach.systems.base import ControlAffineSystem
from reach.systems.box import NO_INPUT, Box
from reach.systems.deepreach_normalisation import DeepReachNormalisation
from reach.validation import positive_finite

ROLES = ("control", "disturbance")


def _check_positive(owner: str, pairs: Sequence[tuple[str, Any]]) -> None:
    for field, value in pairs:
        positive_finite(f"{owner}: {field}", value)


class RelativePair(ControlAffineSystem):
    """Two Dubins cars in car 1's frame; car 2's turn rate is a control or a disturbance.

    The defaults are one pair of the 9D system (v = 0.6, |w| <= 1.1, both controls, R = 0.25,
    T = 1.0) on relative positions in [-1.6, 1.6]^2, which covers every pair that can meet within the
    horizon from the 9D box's near-collision region (farther pairs are safe by the margin bound).
    """

    name = "relativepair"
    state_names = ("x1", "x2", "x3")
    periodic = (False, False, True)

    def __init__(
        self,
        speed_1: float = 0.6,
        speed_2: float = 0.6,
        max_turn_rate_1: float = 1.1,
        max_turn_rate_2: float = 1.1,
        role_2: str = "control",
        collision_radius: float = 0.25,
        horizon: float = 1.0,
        half_width: float = 1.6,
    ) -> None:
        _check_positive(
            "RelativePair",
            (
                ("speed_1", speed_1),
                ("speed_2", speed_2),
                ("max_turn_rate_1", max_turn_rate_1),
                ("max_turn_rate_2", max_turn_rate_2),
                ("collision_radius", collision_radius),
                ("horizon", horizon),
                ("half_width", half_width),
            ),
        )
        if not isinstance(role_2, str) or role_2 not in ROLES:
            raise ValueError(f"RelativePair: role_2 must be one of {ROLES}, got {role_2!r}")
        self._setup(speed_1, speed_2, max_turn_rate_1, max_turn_rate_2, role_2, collision_radius, horizon, half_width)

    def _setup(
        self,
        v1: float,
        v2: float,
        w1: float,
        w2: float,
        role_2: str,
        collision_radius: float,
        horizon: float,
        half_width: float,
    ) -> None:
        self.speed_1, self.speed_2 = float(v1), float(v2)
        self.max_turn_rate_1, self.max_turn_rate_2 = float(w1), float(w2)
        self.role_2 = role_2
        self.collision_radius = float(collision_radius)
        self.horizon = float(horizon)
        self.half_width = float(half_width)
        self.domain = ((-half_width, half_width), (-half_width, half_width), (-math.pi, math.pi))
        if role_2 == "control":
            self.control_bounds = Box.symmetric([w1, w2])
            self.disturbance_bounds = NO_INPUT
        else:
            self.control_bounds = Box.symmetric([w1])
            self.disturbance_bounds = Box.symmetric([w2])
        self.deepreach = DeepReachNormalisation(
            state_offset=(0.0, 0.0, 0.0), state_scale=(half_width, half_width, 1.2 * math.pi)
        )

    def parameters(self) -> dict[str, Any]:
        return {
            "speed_1": self.speed_1,
            "speed_2": self.speed_2,
            "max_turn_rate_1": self.max_turn_rate_1,
            "max_turn_rate_2": self.max_turn_rate_2,
            "role_2": self.role_2,
            "collision_radius": self.collision_radius,
            "horizon": self.horizon,
            "half_width": self.half_width,
        }

    # ------------------------------------------------------------------ physics
    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        _, _, x3 = x
        return [-self.speed_1 + self.speed_2 * xp.cos(x3), self.speed_2 * xp.sin(x3), 0.0]

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        x1, x2, _ = x
        matrix: InputMatrix = {(0, 0): x2, (1, 0): -x1, (2, 0): -1.0}
        if self.role_2 == "control":
            matrix[(2, 1)] = 1.0
        return matrix

    def disturbance_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        return {(2, 0): 1.0} if self.role_2 == "disturbance" else {}

    def margin_rate_bound(self) -> float:
        """``v1 + v2``: turning only rotates the relative position, so only the speeds change ``||(x1, x2)||``."""
        return self.speed_1 + self.speed_2

    def margin_step_bound(self, dt: float, integrator: str) -> float | None:
        """``dt (v1 + v2)`` for Euler steps; ``None`` for RK4.

        An Euler step moves the relative position ``r = (x1, x2)`` to
        ``r + dt w1 (x2, -x1) + dt (-v1 + v2 cos x3, v2 sin x3)``. The first term is perpendicular to
        ``r``, so ``|r + dt w1 (x2, -x1)| = |r| sqrt(1 + (dt w1)^2) >= |r|``; the second has length at
        most ``dt (v1 + v2)``. So ``|r|``, and ``l``, drop by at most ``dt (v1 + v2)``, from any state.
        RK4 approximates the rotation by a polynomial that shrinks ``|r|`` by a factor slightly below
        one, a loss that grows with ``|r|``: no bound holds for every state."""
        if integrator != "euler":
            return None
        return positive_finite("dt", dt) * (self.speed_1 + self.speed_2)

    def margin_outside_domain(self, scale: float = 1.0) -> float:
        """``scale * half_width - R``: outside the square of relative positions (widened ``scale``
        times) ``|r| > scale * half_width``."""
        return positive_finite("scale", scale) * self.half_width - self.collision_radius

    def certification_defaults(self) -> dict[str, Any]:
        """The zero level, closed over the box four times wider with the escape set as far out as
        :meth:`margin_outside_domain` allows there (``4 half_width - R``), on cells of 1/32 of the span
        cut finer three times near the set's edge: the settings of the documented Air3D certificate
        (docs/results/certificates.md), and what the derived defaults give for these lemmas."""
        return {
            "level": 0.0,
            "escape_margin": self.margin_outside_domain(4.0),
            "closure_scale": 4,
            "closure_relative_width": 1 / 32,
            "min_relative_width": 1 / 32,
            "closure_refinements": 3,
        }

    def failure_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        return xp.hypot(x[0], x[1]) - self.collision_radius

    # ------------------------------------------------------------------ geometry (envs, rendering)
    def car_poses(self, x: Sequence[Column], xp: Backend) -> list[tuple[Column, Column, Column]]:
        """(x, y, heading) of car 1 (at the origin, heading 0) and car 2, in car 1's frame."""
        zero = 0.0 * x[0]
        return [(zero, zero, zero), (x[0], x[1], x[2])]

    @property
    def car_names(self) -> tuple[str, ...]:
        return ("car_1", "car_2")

    @property
    def car_roles(self) -> tuple[str, ...]:
        return ("control", self.role_2)

    @property
    def car_max_turn_rates(self) -> tuple[float, ...]:
        return (self.max_turn_rate_1, self.max_turn_rate_2)


class Air3D(RelativePair):
    """Air3D with DeepReach's constants by default (ve = vp = 0.75, |u|, |d| <= 3, R = 0.25, T = 1.1).

    Car 1 is the evader (control ``u``), car 2 the pursuer (disturbance ``d``).
    """

    name = "air3d"

    def __init__(
        self,
        evader_speed: float = 0.75,
        pursuer_speed: float = 0.75,
        evader_max_turn_rate: float = 3.0,
        pursuer_max_turn_rate: float = 3.0,
        collision_radius: float = 0.25,
        horizon: float = 1.1,
        half_width: float = 1.0,
    ) -> None:
        _check_positive(
            "Air3D",
            (
                ("evader_speed", evader_speed),
                ("pursuer_speed", pursuer_speed),
                ("evader_max_turn_rate", evader_max_turn_rate),
                ("pursuer_max_turn_rate", pursuer_max_turn_rate),
                ("collision_radius", collision_radius),
                ("horizon", horizon),
                ("half_width", half_width),
            ),
        )
        self._setup(
            evader_speed,
            pursuer_speed,
            evader_max_turn_rate,
            pursuer_max_turn_rate,
            "disturbance",
            collision_radius,
            horizon,
            half_width,
        )
        # DeepReach leaves positions raw (its Air3D box is [-1, 1]) and divides headings by 1.2 pi
        self.deepreach = DeepReachNormalisation(state_offset=(0.0, 0.0, 0.0), state_scale=(1.0, 1.0, 1.2 * math.pi))

    @property
    def evader_speed(self) -> float:
        return self.speed_1

    @property
    def pursuer_speed(self) -> float:
        return self.speed_2

    @property
    def evader_max_turn_rate(self) -> float:
        return self.max_turn_rate_1

    @property
    def pursuer_max_turn_rate(self) -> float:
        return self.max_turn_rate_2

    def parameters(self) -> dict[str, Any]:
        return {
            "evader_speed": self.evader_speed,
            "pursuer_speed": self.pursuer_speed,
            "evader_max_turn_rate": self.evader_max_turn_rate,
            "pursuer_max_turn_rate": self.pursuer_max_turn_rate,
            "collision_radius": self.collision_radius,
            "horizon": self.horizon,
            "half_width": self.half_width,
        }

    @property
    def car_names(self) -> tuple[str, ...]:
        return ("evader_1", "pursuer_1")

    #: the relative heading of the slice that DeepReach and the MATLAB toolbox report
    REFERENCE_HEADING: ClassVar[float] = 1.5863

    def reference_slice(self) -> tuple[int, float]:
        """The x3 = 1.5863 slice, where DeepReach and the MATLAB toolbox compare Air3D BRTs."""
        return (2, self.REFERENCE_HEADING)

    def plot_slices(self) -> list[tuple[tuple[float, ...], tuple[int, int], str]]:
        """x1-x2 at the reference heading 1.5863, at 0 and at -pi/2."""
        return [((0.0, 0.0, v), (0, 1), f"x3 = {v:.4g}") for v in (self.REFERENCE_HEADING, 0.0, -math.pi / 2)]
