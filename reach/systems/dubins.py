"""Dubins cars posing each kind of problem: DeepReach's Dubins3D (reach or avoid) and a reach-avoid car.

State ``x = (px, py, heading)``, constant speed ``v``, turn rate ``w`` the control::

    px' = v cos(heading) [+ dx]      py' = v sin(heading) [+ dy]      heading' = w

:class:`Dubins3D` restates DeepReach's (public release, ``dynamics.py``): a disc of radius
``goalR`` at the origin that the car must reach (``set_mode="reach"``) or avoid
(``set_mode="avoid"``), with its constants as defaults. :class:`DubinsReachAvoid` must reach a goal
disc while keeping out of an obstacle disc, against a bounded wind ``(dx, dy)``: the reach-avoid
problem a robot meets first.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from reach.systems.arrays import Backend, Column, InputMatrix
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Box
from reach.systems.deepreach_normalisation import DeepReachNormalisation
from reach.validation import finite_point, positive_finite

#: DeepReach's ``set_mode`` values and the kind each poses
SET_MODES = {"reach": "reach", "avoid": "avoid"}


def _disc_margin(x: Sequence[Column], xp: Backend, centre: Sequence[float], radius: float) -> Column:
    """Signed distance from the car's position to a disc: negative inside it."""
    return xp.hypot(x[0] - centre[0], x[1] - centre[1]) - radius


class Dubins3D(ControlAffineSystem):
    """DeepReach's Dubins3D: reach (or avoid) a disc of radius ``goalR`` at the origin.

    Defaults are DeepReach's (``goalR 0.25, velocity 0.6, omega_max 1.1``, positions in [-1, 1]^2,
    ``angle_alpha_factor`` 1.2 in its heading normalisation) and a 1 s horizon.
    """

    name = "dubins3d"
    state_names = ("px", "py", "heading")
    periodic = (False, False, True)

    def __init__(
        self,
        set_mode: str = "reach",
        goalR: float = 0.25,
        velocity: float = 0.6,
        omega_max: float = 1.1,
        horizon: float = 1.0,
    ) -> None:
        if not isinstance(set_mode, str) or set_mode not in SET_MODES:
            raise ValueError(f"Dubins3D: set_mode must be one of {tuple(SET_MODES)}, got {set_mode!r}")
        self.set_mode = set_mode
        self.kind = SET_MODES[set_mode]
        self.goalR = positive_finite("Dubins3D: goalR", goalR)
        self.velocity = positive_finite("Dubins3D: velocity", velocity)
        self.omega_max = positive_finite("Dubins3D: omega_max", omega_max)
        self.horizon = positive_finite("Dubins3D: horizon", horizon)
        self.domain = ((-1.0, 1.0), (-1.0, 1.0), (-math.pi, math.pi))
        self.control_bounds = Box.symmetric([self.omega_max])
        self.deepreach = DeepReachNormalisation(
            state_offset=(0.0, 0.0, 0.0), state_scale=(1.0, 1.0, 1.2 * math.pi), model="diff"
        )

    def parameters(self) -> dict[str, Any]:
        return {
            "set_mode": self.set_mode,
            "goalR": self.goalR,
            "velocity": self.velocity,
            "omega_max": self.omega_max,
            "horizon": self.horizon,
        }

    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        return [self.velocity * xp.cos(x[2]), self.velocity * xp.sin(x[2]), 0.0 * x[2]]

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        return {(2, 0): 1.0}

    def _disc(self, x: Sequence[Column], xp: Backend) -> Column:
        return _disc_margin(x, xp, (0.0, 0.0), self.goalR)

    def target_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        if self.kind != "reach":
            return super().target_margin_columns(x, xp)  # an avoid problem has no target
        return self._disc(x, xp)

    def failure_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        if self.kind != "avoid":
            return super().failure_margin_columns(x, xp)  # a reach problem has no failure set
        return self._disc(x, xp)

    def margin_rate_bound(self) -> float:
        return self.velocity

    def target_floor(self, x: torch.Tensor, time: float) -> torch.Tensor | None:
        """``l(x) - v time`` (reach): the target margin is the distance to the goal disc's edge, and the
        car moves no faster than ``v``; an Euler or RK4 step moves it by a weighted mean of stage
        velocities of length ``v`` with positive weights summing to one, so by at most ``dt v`` too."""
        if self.kind != "reach":
            return None
        return self.target_margin(x) - self.velocity * time

    def margin_step_bound(self, dt: float, integrator: str) -> float | None:
        """``dt v`` (avoid; Euler or RK4): either step moves the position by a weighted mean of
        stage velocities, each of length ``v``, with positive weights summing to one, so by at most
        ``dt v``; ``l`` is a distance, which changes no faster than the position."""
        if self.kind != "avoid":
            return None
        return positive_finite("dt", dt) * self.velocity

    def margin_outside_domain(self, scale: float = 1.0) -> float | None:
        """``scale - goalR`` (avoid): outside the square ``[-scale, scale]^2`` the car is farther than
        ``scale`` from the disc's centre."""
        return positive_finite("scale", scale) - self.goalR if self.kind == "avoid" else None


class DubinsReachAvoid(ControlAffineSystem):
    """A Dubins car that must reach a goal disc within the horizon, keeping out of an obstacle disc,
    whatever a bounded wind ``(dx, dy)`` does.

    Defaults: speed 0.6, turn rate within 1.1 rad/s, wind within 0.1 per axis, goal of radius 0.2 at
    (0.7, 0), obstacle of radius 0.25 at (0.1, 0), positions in [-1, 1]^2, a 2 s horizon.
    """

    name = "dubinsreachavoid"
    kind = "reach-avoid"
    state_names = ("px", "py", "heading")
    periodic = (False, False, True)

    def __init__(
        self,
        speed: float = 0.6,
        max_turn_rate: float = 1.1,
        wind: float = 0.1,
        goal: tuple[float, float] = (0.7, 0.0),
        goal_radius: float = 0.2,
        obstacle: tuple[float, float] = (0.1, 0.0),
        obstacle_radius: float = 0.25,
        horizon: float = 2.0,
    ) -> None:
        self.speed = positive_finite("DubinsReachAvoid: speed", speed)
        self.max_turn_rate = positive_finite("DubinsReachAvoid: max_turn_rate", max_turn_rate)
        self.wind = positive_finite("DubinsReachAvoid: wind", wind)
        self.goal = finite_point("DubinsReachAvoid: goal", goal, 2)
        self.goal_radius = positive_finite("DubinsReachAvoid: goal_radius", goal_radius)
        self.obstacle = finite_point("DubinsReachAvoid: obstacle", obstacle, 2)
        self.obstacle_radius = positive_finite("DubinsReachAvoid: obstacle_radius", obstacle_radius)
        self.horizon = positive_finite("DubinsReachAvoid: horizon", horizon)
        self.domain = ((-1.0, 1.0), (-1.0, 1.0), (-math.pi, math.pi))
        self.control_bounds = Box.symmetric([self.max_turn_rate])
        self.disturbance_bounds = Box.symmetric([self.wind, self.wind])

    def parameters(self) -> dict[str, Any]:
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

    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        return [self.speed * xp.cos(x[2]), self.speed * xp.sin(x[2]), 0.0 * x[2]]

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        return {(2, 0): 1.0}

    def disturbance_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        return {(0, 0): 1.0, (1, 1): 1.0}

    def target_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        return _disc_margin(x, xp, self.goal, self.goal_radius)

    def constraint_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        return _disc_margin(x, xp, self.obstacle, self.obstacle_radius)

    def margin_rate_bound(self) -> float:
        return self.speed + math.sqrt(2.0) * self.wind

    def target_floor(self, x: torch.Tensor, time: float) -> torch.Tensor:
        """``l(x) - (v + sqrt(2) w) time``: the target margin is the distance to the goal disc's edge,
        and the car's velocity, its own plus the wind, is no longer than ``v + sqrt(2) w``; an Euler or
        RK4 step moves it by a weighted mean of such stage velocities, with positive weights summing
        to one, so by at most ``dt`` times that. (The same bound holds for the obstacle's margin, the
        constraint: :meth:`margin_floor`.)"""
        return self.target_margin(x) - self.margin_rate_bound() * time


__all__ = ["SET_MODES", "Dubins3D", "DubinsReachAvoid"]
