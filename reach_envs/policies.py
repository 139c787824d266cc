"""Who drives the disturbance in a scene: scripted, random, or any callable policy of the state.

Built-in policies work on state columns with a backend, so one implementation serves the single
environment (Python floats) and the vector environment (NumPy batches). Policies return
disturbances in physical units; the simulator clips them to the system's disturbance box.

``"pursue"`` means :class:`PursuitPolicy` for vehicle systems (disturbance cars chase control cars)
and :class:`MarginPursuit` for any other system (the disturbance plays its side of the game on the
margins: toward the failure set of an avoid system, away from the goal or toward an obstacle of a
reach kind).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from reach.systems.arrays import FLOAT, Backend, Column
from reach.systems.base import ControlAffineSystem
from reach.validation import positive_finite


class DisturbancePolicy(Protocol):
    """``columns(x, xp, rng) -> d``: one column per disturbance input, physical units."""

    def columns(self, x: Sequence[Column], xp: Backend, rng: np.random.Generator) -> list[Column]: ...


def _require_vehicles(system: ControlAffineSystem, what: str) -> None:
    if not hasattr(system, "car_poses"):
        raise ValueError(f"{what} needs a vehicle system with car_poses(); {system.name} has none")


class PursuitPolicy:
    """Each disturbance car turns toward the nearest control car: ``d = clip(gain * heading error)``.

    The heading error is the wrapped angle between the car's heading and the bearing to its target,
    so the pursuer turns at full rate when far off course and smoothly when nearly aligned.
    """

    def __init__(self, system: ControlAffineSystem, gain: float = 4.0) -> None:
        _require_vehicles(system, "PursuitPolicy")
        self.system = system
        self.gain = positive_finite("PursuitPolicy: gain", gain)
        roles = system.car_roles
        self._controls = [i for i, r in enumerate(roles) if r == "control"]
        self._pursuers = [i for i, r in enumerate(roles) if r == "disturbance"]
        self._limits = [system.car_max_turn_rates[i] for i in self._pursuers]

    def columns(self, x: Sequence[Column], xp: Backend, rng: np.random.Generator) -> list[Column]:
        poses = self.system.car_poses(x, xp)
        out: list[Column] = []
        for k, limit in zip(self._pursuers, self._limits):
            px, py, th = poses[k]
            best_dx = best_dy = best_r2 = None
            for c in self._controls:
                cx, cy, _ = poses[c]
                dx, dy = cx - px, cy - py
                r2 = dx * dx + dy * dy
                if best_r2 is None:
                    best_dx, best_dy, best_r2 = dx, dy, r2
                else:
                    closer = r2 < best_r2
                    best_dx = xp.where(closer, dx, best_dx)
                    best_dy = xp.where(closer, dy, best_dy)
                    best_r2 = xp.minimum(r2, best_r2)
            error = xp.wrap_angle(xp.atan2(best_dy, best_dx) - th)
            out.append(xp.clip(self.gain * error, -limit, limit))
        return out


class MarginPursuit:
    """The disturbance that plays its side of the game on the margins, for any system: the corner of
    the disturbance box that the system's own optimal-input rule picks for the costate ``p = grad m(x)``
    of one margin ``m``; the box centre along inputs that do not move ``m``.

    ``m`` is the failure margin of an avoid system (the disturbance minimises it: toward the failure
    set) and the target margin ``l`` of a reach system (the disturbance maximises it: away from the
    goal). A reach-avoid disturbance goes for the nearer of its two wins: away from the goal (``m = l``)
    where ``l(x) <= g(x)``, else toward the obstacles (``m = -g``, the constraint margin turned so that
    maximising it closes in).

    The gradient is a central difference, taken only along the state dimensions the disturbance
    enters (two margin evaluations each), with a step of ``1e-6`` times each dimension's domain width.
    """

    def __init__(self, system: ControlAffineSystem, rel_step: float = 1e-6) -> None:
        rel_step = positive_finite("MarginPursuit: rel_step", rel_step)
        self.system = system
        self._steps = [rel_step * (hi - lo) for lo, hi in system.domain]

    def _gradient(self, margin: Callable[..., Column], x: Sequence[Column], xp: Backend) -> list[Column]:
        """``grad margin(x)`` along the dimensions the disturbance enters, 0 along the others."""
        p: list[Column] = [0.0] * self.system.state_dim
        for i in sorted({i for i, _ in self.system.disturbance_matrix(x, xp)}):
            h = self._steps[i]
            up, down = list(x), list(x)
            up[i] = x[i] + h
            down[i] = x[i] - h
            p[i] = (margin(up, xp) - margin(down, xp)) / (2.0 * h)
        return p

    def columns(self, x: Sequence[Column], xp: Backend, rng: np.random.Generator) -> list[Column]:
        system = self.system
        if not system.problem.reaches:
            p = self._gradient(system.failure_margin_columns, x, xp)
        elif not system.problem.has_constraint:
            p = self._gradient(system.target_margin_columns, x, xp)
        else:
            near_goal = system.target_margin_columns(x, xp) <= system.constraint_margin_columns(x, xp)
            to_goal = self._gradient(system.target_margin_columns, x, xp)
            to_obstacle = self._gradient(system.constraint_margin_columns, x, xp)
            p = [xp.where(near_goal, a, -b) for a, b in zip(to_goal, to_obstacle)]
        return system.optimal_inputs_columns(x, p, xp)[1]


class RandomDisturbance:
    """Disturbance drawn uniformly from its box at every step (uses the environment's generator)."""

    def __init__(self, system: ControlAffineSystem) -> None:
        self.low = np.array(system.disturbance_bounds.low)
        self.high = np.array(system.disturbance_bounds.high)
        self._bounds = list(zip(system.disturbance_bounds.low, system.disturbance_bounds.high))

    def columns(self, x: Sequence[Column], xp: Backend, rng: np.random.Generator) -> list[Column]:
        if xp is FLOAT:  # one scalar draw per input: cheaper than an array call at batch size 1
            return [lo + (hi - lo) * rng.random() for lo, hi in self._bounds]
        batch = np.shape(x[0])
        d = rng.uniform(self.low, self.high, size=batch + self.low.shape)
        return [d[..., k] for k in range(self.low.shape[0])]


class CallableDisturbance:
    """Adapts a user function ``state -> disturbance`` (physical units) to the policy protocol.

    In a single environment the function receives the state as a float64 array ``(n,)`` and returns
    ``(m_d,)``; in a vector environment it receives ``(num_envs, n)`` and returns ``(num_envs, m_d)``.
    Non-finite or wrongly shaped results raise ``ValueError``.
    """

    def __init__(self, system: ControlAffineSystem, fn: Callable[[np.ndarray], Any]) -> None:
        self.fn = fn
        self.dim = system.disturbance_dim

    def columns(self, x: Sequence[Column], xp: Backend, rng: np.random.Generator) -> list[Column]:
        state = np.array(x, dtype=np.float64) if xp is FLOAT else np.stack(x, axis=-1)
        d = np.asarray(self.fn(state), dtype=np.float64)
        expected = (*state.shape[:-1], self.dim)
        if d.shape != expected:
            raise ValueError(f"disturbance policy returned shape {d.shape}, expected {expected}")
        if not np.isfinite(d).all():
            raise ValueError(f"disturbance policy returned a non-finite value: {d}")
        return d.tolist() if xp is FLOAT else [d[..., k] for k in range(self.dim)]


#: Names accepted by ``Scene(disturbance=...)``; ``None`` means no disturbance policy at all.
DISTURBANCE_KINDS = ("pursue", "random")


def make_disturbance_policy(system: ControlAffineSystem, spec: Any) -> DisturbancePolicy | None:
    """Resolve a scene's ``disturbance`` field into a policy (``None`` for no disturbance)."""
    if spec is None or spec == "none":
        return None
    if system.disturbance_dim == 0:
        raise ValueError(f"disturbance={spec!r} given, but system {system.name} has no disturbance input")
    if spec == "pursue":
        return PursuitPolicy(system) if hasattr(system, "car_poses") else MarginPursuit(system)
    if spec == "random":
        return RandomDisturbance(system)
    if hasattr(spec, "columns"):
        return spec
    if callable(spec):
        return CallableDisturbance(system, spec)
    raise ValueError(f"disturbance must be None, one of {DISTURBANCE_KINDS} or a callable, got {spec!r}")
