"""Air3D: two-aircraft pursuit-evasion in the evader's frame (Mitchell et al. 2005; DeepReach).

State ``x = (x1, x2, x3)``: the pursuer's position and heading relative to the evader::

    x1' = -ve + vp cos x3 + u x2
    x2' =        vp sin x3 - u x1
    x3' = d - u

``u`` is the evader's turn rate (control, keeps safe), ``d`` the pursuer's turn rate (disturbance).
Failure: the pursuer within ``collision_radius`` of the evader, ``l(x) = ||(x1, x2)|| - R``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from reach_envs.systems.backend import Backend, Column
from reach_envs.systems.base import Box, ControlAffineSystem, DeepReachNormalisation, InputMatrix


class Air3D(ControlAffineSystem):
    """Air3D with DeepReach's constants by default (ve = vp = 0.75, |u|, |d| <= 3, R = 0.25, T = 1.1)."""

    name = "air3d"
    state_names = ("x1", "x2", "x3")
    periodic = (False, False, True)

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
        for field, value in (
            ("evader_speed", evader_speed),
            ("pursuer_speed", pursuer_speed),
            ("evader_max_turn_rate", evader_max_turn_rate),
            ("pursuer_max_turn_rate", pursuer_max_turn_rate),
            ("collision_radius", collision_radius),
            ("half_width", half_width),
        ):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"Air3D: {field} must be a positive finite number, got {value!r}")
        self.evader_speed = float(evader_speed)
        self.pursuer_speed = float(pursuer_speed)
        self.evader_max_turn_rate = float(evader_max_turn_rate)
        self.pursuer_max_turn_rate = float(pursuer_max_turn_rate)
        self.collision_radius = float(collision_radius)
        self.horizon = float(horizon)
        self.half_width = float(half_width)
        self.domain = ((-half_width, half_width), (-half_width, half_width), (-math.pi, math.pi))
        self.control_bounds = Box.symmetric([evader_max_turn_rate])
        self.disturbance_bounds = Box.symmetric([pursuer_max_turn_rate])
        self.deepreach = DeepReachNormalisation(state_offset=(0.0, 0.0, 0.0), state_scale=(1.0, 1.0, 1.2 * math.pi))
        self.validate()

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

    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        _, _, x3 = x
        return [-self.evader_speed + self.pursuer_speed * xp.cos(x3), self.pursuer_speed * xp.sin(x3), 0.0]

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        x1, x2, _ = x
        return {(0, 0): x2, (1, 0): -x1, (2, 0): -1.0}

    def disturbance_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        return {(2, 0): 1.0}

    def margin_rate_bound(self) -> float:
        """``ve + vp``: turning only rotates the relative position, so only the speeds change ``||(x1, x2)||``."""
        return self.evader_speed + self.pursuer_speed

    def failure_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        return xp.hypot(x[0], x[1]) - self.collision_radius

    # ------------------------------------------------------------------ geometry (envs, rendering)
    def car_poses(self, x: Sequence[Column], xp: Backend) -> list[tuple[Column, Column, Column]]:
        """(x, y, heading) of the evader (at the origin, heading 0) and the pursuer, evader frame."""
        zero = 0.0 * x[0]
        return [(zero, zero, zero), (x[0], x[1], x[2])]

    car_names = ("evader_1", "pursuer_1")
    car_roles = ("control", "disturbance")

    @property
    def car_max_turn_rates(self) -> tuple[float, ...]:
        return (self.evader_max_turn_rate, self.pursuer_max_turn_rate)
