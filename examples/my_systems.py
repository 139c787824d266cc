"""Three systems that are not in the package, defined the way a user defines theirs.

Used by the tutorial (docs/custom_system.md) and by the tests. Each declares physics only: states,
domain, input boxes, the control-affine dynamics ``x' = f(x) + G_u(x) u + G_d(x) d``, its kind of
problem and its margins (the failure margin ``l(x)`` of an avoid problem; the target margin and the
constraint margin of a reach-avoid one); every tool of the toolkit derives the rest.

Refer to them as ``my_systems:DubinsAvoid``, ``my_systems:DubinsAccel`` and ``my_systems:DubinsGap``
with this folder on the import path (``PYTHONPATH=examples``), or by their registered names after
``import my_systems``.
"""

from __future__ import annotations

import math

from reach.systems import Box, ControlAffineSystem, register_system


@register_system
class DubinsAvoid(ControlAffineSystem):
    """A Dubins car at constant speed avoiding an off-centre disc, pushed by a bounded wind (dx, dy)."""

    name = "dubins-avoid"
    state_names = ("px", "py", "heading")
    periodic = (False, False, True)

    def __init__(
        self,
        speed: float = 0.8,
        max_turn_rate: float = 1.5,
        wind: float = 0.1,
        centre: tuple[float, float] = (0.3, 0.2),
        radius: float = 0.4,
        horizon: float = 1.0,
    ) -> None:
        self.speed, self.max_turn_rate, self.wind = speed, max_turn_rate, wind
        self.centre, self.radius, self.horizon = tuple(centre), radius, horizon
        self.domain = ((-1.5, 1.5), (-1.5, 1.5), (-math.pi, math.pi))
        self.control_bounds = Box.symmetric([max_turn_rate])
        self.disturbance_bounds = Box.symmetric([wind, wind])

    def parameters(self) -> dict:
        return {
            "speed": self.speed,
            "max_turn_rate": self.max_turn_rate,
            "wind": self.wind,
            "centre": list(self.centre),
            "radius": self.radius,
            "horizon": self.horizon,
        }

    def drift(self, x, xp):
        return [self.speed * xp.cos(x[2]), self.speed * xp.sin(x[2]), 0.0 * x[2]]

    def control_matrix(self, x, xp):
        return {(2, 0): 1.0}

    def disturbance_matrix(self, x, xp):
        return {(0, 0): 1.0, (1, 1): 1.0}

    def failure_margin_columns(self, x, xp):
        return xp.sqrt((x[0] - self.centre[0]) ** 2 + (x[1] - self.centre[1]) ** 2) - self.radius

    def margin_rate_bound(self) -> float:
        return self.speed + math.sqrt(2.0) * self.wind


@register_system
class DubinsAccel(ControlAffineSystem):
    """A 4D car that steers and accelerates (two controls) around a disc, with wind on both positions."""

    name = "dubins-accel"
    state_names = ("px", "py", "heading", "speed")
    periodic = (False, False, True, False)

    def __init__(
        self,
        max_turn_rate: float = 1.5,
        max_accel: float = 1.0,
        wind: float = 0.05,
        radius: float = 0.4,
        horizon: float = 1.0,
    ) -> None:
        self.max_turn_rate, self.max_accel, self.wind = max_turn_rate, max_accel, wind
        self.radius, self.horizon = radius, horizon
        self.domain = ((-1.5, 1.5), (-1.5, 1.5), (-math.pi, math.pi), (0.0, 1.2))
        self.control_bounds = Box.symmetric([max_turn_rate, max_accel])
        self.disturbance_bounds = Box.symmetric([wind, wind])

    def parameters(self) -> dict:
        return {
            "max_turn_rate": self.max_turn_rate,
            "max_accel": self.max_accel,
            "wind": self.wind,
            "radius": self.radius,
            "horizon": self.horizon,
        }

    def drift(self, x, xp):
        return [x[3] * xp.cos(x[2]), x[3] * xp.sin(x[2]), 0.0 * x[2], 0.0 * x[3]]

    def control_matrix(self, x, xp):
        return {(2, 0): 1.0, (3, 1): 1.0}

    def disturbance_matrix(self, x, xp):
        return {(0, 0): 1.0, (1, 1): 1.0}

    def failure_margin_columns(self, x, xp):
        return xp.sqrt(x[0] ** 2 + x[1] ** 2) - self.radius


@register_system
class DubinsGap(ControlAffineSystem):
    """A reach-avoid problem: a Dubins car must reach a goal disc within the horizon through the gap
    between two round obstacles, whatever a bounded wind (dx, dy) does."""

    name = "dubins-gap"
    kind = "reach-avoid"
    state_names = ("px", "py", "heading")
    periodic = (False, False, True)

    def __init__(
        self,
        speed: float = 0.8,
        max_turn_rate: float = 1.5,
        wind: float = 0.1,
        goal: tuple[float, float] = (1.0, 0.0),
        goal_radius: float = 0.25,
        gap: float = 0.3,
        obstacle_radius: float = 0.3,
        horizon: float = 1.5,
    ) -> None:
        self.speed, self.max_turn_rate, self.wind = speed, max_turn_rate, wind
        self.goal, self.goal_radius = tuple(goal), goal_radius
        self.gap, self.obstacle_radius, self.horizon = gap, obstacle_radius, horizon
        self.domain = ((-1.5, 1.5), (-1.5, 1.5), (-math.pi, math.pi))
        self.control_bounds = Box.symmetric([max_turn_rate])
        self.disturbance_bounds = Box.symmetric([wind, wind])

    def parameters(self) -> dict:
        return {
            "speed": self.speed,
            "max_turn_rate": self.max_turn_rate,
            "wind": self.wind,
            "goal": list(self.goal),
            "goal_radius": self.goal_radius,
            "gap": self.gap,
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
        """Positive away from both obstacles: discs at (0.2, +-(gap / 2 + radius)), a gap between."""
        offset = self.gap / 2 + self.obstacle_radius
        upper = xp.hypot(x[0] - 0.2, x[1] - offset) - self.obstacle_radius
        lower = xp.hypot(x[0] - 0.2, x[1] + offset) - self.obstacle_radius
        return xp.minimum(upper, lower)

    def margin_rate_bound(self) -> float:
        return self.speed + math.sqrt(2.0) * self.wind


def cruise(states):
    """A nominal policy for DubinsAccel that ignores safety: no turn, accelerate toward speed 0.8.

    Float64 states ``(N, 4)`` in, actions ``(N, 2)`` normalised to [-1, 1] out (turn rate, acceleration).
    """
    import numpy as np

    accel = np.clip(2.0 * (0.8 - states[:, 3]), -1.0, 1.0)
    return np.stack([np.zeros(len(states)), accel], axis=-1)


def head_for_goal(states):
    """A nominal policy for DubinsGap that ignores the obstacles: turn toward the goal's centre.

    Float64 states ``(N, 3)`` in, actions ``(N, 1)`` normalised to [-1, 1] out (turn rate).
    """
    import numpy as np

    bearing = np.arctan2(0.0 - states[:, 1], 1.0 - states[:, 0])
    error = (bearing - states[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return np.clip(3.0 * error, -1.0, 1.0)[:, None]
