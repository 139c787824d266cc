"""Tasks for safety-filter evaluation: goals for the controlled cars and nominal policies that ignore safety.

A task lives beside the environment, not inside it (the scene simulates physics only): it reads the
batched states, proposes nominal actions (normalised to [-1, 1] like the environments' actions) and
tracks goal progress from the states and the inputs actually applied. Everything is batched over
episodes in NumPy.

* :class:`WaypointTask` (multi-vehicle scenes, absolute coordinates): each control car drives to a
  waypoint ``distance`` ahead of its initial pose (through the conflict zone of the crossing and
  merge scenes) and turns toward it at a bounded rate.
* :class:`EvaderGoalTask` (Air3D, relative coordinates): the state says where the pursuer is relative
  to the evader, not where the evader is, so the task integrates the evader's world pose itself (exact
  arcs under the applied turn rate) and steers it to a goal drawn per episode.
* :class:`NominalTask` (any avoid system, a user's own included): no goal; the nominal policy is a
  callable the user supplies, or by default "keep the nominal input" (the centre of the control box).
* :class:`TargetTask` (reach and reach-avoid systems): the goal is the system's own target set
  (``target_margin <= 0``); the nominal policy is the user's, or by default one that heads for the
  target and ignores every obstacle (:func:`head_for_target`).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable

import numpy as np
import torch

from reach.integrators import make_stepper
from reach.systems import NUMPY, TORCH, ControlAffineSystem, MultiVehicle, RelativePair
from reach.validation import positive_finite

_wrap = NUMPY.wrap_angle  # the package's one angle wrap, on NumPy arrays


class GoalTask(ABC):
    """Goal-seeking nominal policy plus goal bookkeeping for ``N`` parallel episodes."""

    #: whether the task has goals (a task without, :class:`NominalTask`, reports no goal rate)
    has_goal = True

    def __init__(self, system: ControlAffineSystem, goal_radius: float, gain: float) -> None:
        self.system = system
        self.goal_radius = positive_finite(f"{type(self).__name__}: goal_radius", goal_radius)
        self.gain = positive_finite(f"{type(self).__name__}: gain", gain)
        self.half = np.array(system.control_bounds.half_width)
        self.reached = np.zeros(0, dtype=bool)
        self.reach_time = np.zeros(0)

    @abstractmethod
    def reset(self, states: np.ndarray, rng: np.random.Generator) -> None:
        """Start ``len(states)`` episodes from float64 states ``(N, n)``."""

    @abstractmethod
    def nominal_actions(self, states: np.ndarray) -> np.ndarray:
        """Normalised nominal actions ``(N, m_u)`` that steer toward the goals and ignore safety."""

    @abstractmethod
    def advance(self, states: np.ndarray, applied: np.ndarray, dt: float, active: np.ndarray, time: float) -> None:
        """Record one step: post-step states, applied inputs ``(N, m_u)`` (physical units), which
        episodes were still running, and the time at the end of the step."""

    def _steer(self, heading_error: np.ndarray, limit: np.ndarray) -> np.ndarray:
        return np.clip(self.gain * heading_error / limit, -1.0, 1.0)

    def _mark(self, done_now: np.ndarray, active: np.ndarray, time: float) -> None:
        new = done_now & active & ~self.reached
        self.reach_time[new] = time
        self.reached |= new


class WaypointTask(GoalTask):
    """Each control car of a multi-vehicle scene heads for a waypoint ahead of its start."""

    def __init__(
        self, system: MultiVehicle, distance: float = 1.0, goal_radius: float = 0.15, gain: float = 3.0
    ) -> None:
        if not isinstance(system, MultiVehicle):
            raise ValueError(f"WaypointTask needs a multi-vehicle scene, got {system.name}")
        super().__init__(system, goal_radius, gain)
        self.distance = float(distance)
        self.cars = list(system.control_cars)
        self.limits = np.array([system.cars[i].max_turn_rate for i in self.cars])
        self.goals = np.zeros((0, len(self.cars), 2))
        self.car_reached = np.zeros((0, len(self.cars)), dtype=bool)

    def _poses(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = self.system.num_cars
        idx = np.array(self.cars)
        return states[:, 2 * idx], states[:, 2 * idx + 1], states[:, 2 * n + idx]

    def reset(self, states: np.ndarray, rng: np.random.Generator) -> None:
        x, y, th = self._poses(states)
        self.goals = np.stack([x + self.distance * np.cos(th), y + self.distance * np.sin(th)], axis=-1)
        self.car_reached = np.zeros(x.shape, dtype=bool)
        self.reached = np.zeros(len(states), dtype=bool)
        self.reach_time = np.full(len(states), np.nan)

    def nominal_actions(self, states: np.ndarray) -> np.ndarray:
        x, y, th = self._poses(states)
        bearing = np.arctan2(self.goals[..., 1] - y, self.goals[..., 0] - x)
        return self._steer(_wrap(bearing - th), self.limits)

    def advance(self, states: np.ndarray, applied: np.ndarray, dt: float, active: np.ndarray, time: float) -> None:
        x, y, _ = self._poses(states)
        near = np.hypot(self.goals[..., 0] - x, self.goals[..., 1] - y) <= self.goal_radius
        self.car_reached |= near & active[:, None]
        self._mark(self.car_reached.all(axis=1), active, time)


class EvaderGoalTask(GoalTask):
    """Air3D's evader heads for a goal ``distance`` away at a bearing drawn in ``[-spread, spread]``."""

    def __init__(
        self,
        system: RelativePair,
        distance: float = 0.7,
        spread: float = math.pi / 4,
        goal_radius: float = 0.15,
        gain: float = 3.0,
    ) -> None:
        if not isinstance(system, RelativePair):
            raise ValueError(f"EvaderGoalTask needs Air3D (a relative two-car system), got {system.name}")
        super().__init__(system, goal_radius, gain)
        self.distance, self.spread = float(distance), float(spread)
        self.speed = system.speed_1
        self.limit = np.array([system.max_turn_rate_1])
        self.pose = np.zeros((0, 3))
        self.goals = np.zeros((0, 2))

    def reset(self, states: np.ndarray, rng: np.random.Generator) -> None:
        n = len(states)
        bearing = rng.uniform(-self.spread, self.spread, size=n)
        self.goals = self.distance * np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
        self.pose = np.zeros((n, 3))  # the evader's world pose; the relative frame starts on it
        self.reached = np.zeros(n, dtype=bool)
        self.reach_time = np.full(n, np.nan)

    def nominal_actions(self, states: np.ndarray) -> np.ndarray:
        x, y, th = self.pose.T
        bearing = np.arctan2(self.goals[:, 1] - y, self.goals[:, 0] - x)
        return self._steer(_wrap(bearing - th)[:, None], self.limit)

    def advance(self, states: np.ndarray, applied: np.ndarray, dt: float, active: np.ndarray, time: float) -> None:
        x, y, th = self.pose.T
        w = applied[:, 0]
        th_new = th + w * dt
        turning = np.abs(w) > 1e-9
        safe_w = np.where(turning, w, 1.0)
        dx = np.where(turning, self.speed / safe_w * (np.sin(th_new) - np.sin(th)), self.speed * dt * np.cos(th))
        dy = np.where(turning, self.speed / safe_w * (np.cos(th) - np.cos(th_new)), self.speed * dt * np.sin(th))
        moved = np.stack([x + dx, y + dy, _wrap(th_new)], axis=-1)
        self.pose = np.where(active[:, None], moved, self.pose)
        near = np.hypot(self.goals[:, 0] - self.pose[:, 0], self.goals[:, 1] - self.pose[:, 1]) <= self.goal_radius
        self._mark(near, active, time)


#: a nominal policy: float64 states ``(N, n)`` -> actions ``(N, m_u)`` normalised to [-1, 1]
NominalPolicy = Callable[[np.ndarray], np.ndarray]


class NominalTask(GoalTask):
    """No goal: nominal actions from ``policy(states)`` (normalised to [-1, 1], one row per episode),
    or the centre of the control box when ``policy`` is None ("keep the nominal input").

    A policy's output is checked every step: a wrong shape or a non-finite entry raises
    ``ValueError`` instead of reaching the filter as a nominal input.
    """

    has_goal = False

    def __init__(self, system: ControlAffineSystem, policy: NominalPolicy | None = None) -> None:
        if policy is not None and not callable(policy):
            raise ValueError(f"NominalTask: policy must be callable (states -> actions), got {policy!r}")
        self.system = system
        self.policy = policy
        self.half = np.array(system.control_bounds.half_width)
        self.reached = np.zeros(0, dtype=bool)
        self.reach_time = np.zeros(0)

    def reset(self, states: np.ndarray, rng: np.random.Generator) -> None:
        self.reached = np.zeros(len(states), dtype=bool)
        self.reach_time = np.full(len(states), np.nan)

    def nominal_actions(self, states: np.ndarray) -> np.ndarray:
        shape = (len(states), self.system.control_dim)
        if self.policy is None:
            return np.zeros(shape)
        actions = np.asarray(self.policy(states), dtype=np.float64)
        if actions.shape != shape:
            raise ValueError(f"nominal policy returned shape {actions.shape}, expected {shape} (states, controls)")
        if not np.isfinite(actions).all():
            raise ValueError("nominal policy returned a non-finite action")
        return actions

    def advance(self, states: np.ndarray, applied: np.ndarray, dt: float, active: np.ndarray, time: float) -> None:
        return None


#: how far ahead (seconds) and in how many steps :func:`head_for_target` looks
LOOKAHEAD_S = 0.5
LOOKAHEAD_STEPS = 10


def head_for_target(system: ControlAffineSystem) -> NominalPolicy:
    """A nominal policy for a reach kind that heads for the target and ignores every obstacle: among
    the control box's corners and centre, the input that, held for :data:`LOOKAHEAD_S` seconds with
    no disturbance, ends with the smallest target margin (ties: the first candidate, the centre).

    Derived from the system alone, so a user's reach system gets one too; a policy that steers by the
    target margin's gradient alone would not turn a car (a disc's margin does not depend on heading)."""
    system.require_kind(("reach", "reach-avoid"), "head_for_target")
    m = system.control_dim
    corners = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=torch.float64)] * m).reshape(-1, m)
    candidates = torch.cat([torch.zeros(1, m, dtype=torch.float64), corners])  # normalised to [-1, 1]
    centre = torch.tensor(system.control_bounds.center, dtype=torch.float64)
    half = torch.tensor(system.control_bounds.half_width, dtype=torch.float64)
    step = make_stepper(system, LOOKAHEAD_S / LOOKAHEAD_STEPS, "rk4", TORCH)
    d = list(system.disturbance_bounds.center)

    def policy(states: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(states, dtype=torch.float64)
        n, k = x.shape[0], candidates.shape[0]
        cols = TORCH.unbind(x.repeat_interleave(k, dim=0))
        u = TORCH.unbind(centre + half * candidates.repeat(n, 1))
        for _ in range(LOOKAHEAD_STEPS):
            cols = step(cols, u, d)
        margin = system.target_margin(TORCH.stack(cols, like=cols[0])).reshape(n, k)
        return candidates[margin.argmin(dim=1)].numpy()

    return policy


class TargetTask(NominalTask):
    """A reach or reach-avoid system's own task: reach its target set in time. Nominal actions come
    from ``policy`` (default :func:`head_for_target`, checked every step as :class:`NominalTask`
    checks its policy's), and an episode has reached the goal once a running, collision-free
    episode's state has ``target_margin <= 0``."""

    has_goal = True

    def __init__(self, system: ControlAffineSystem, policy: NominalPolicy | None = None) -> None:
        system.require_kind(("reach", "reach-avoid"), "TargetTask")
        super().__init__(system, policy if policy is not None else head_for_target(system))

    def advance(self, states: np.ndarray, applied: np.ndarray, dt: float, active: np.ndarray, time: float) -> None:
        margin = self.system.target_margin(torch.as_tensor(states, dtype=torch.float64)).numpy()
        self._mark(margin <= 0, active, time)


def make_task(system: ControlAffineSystem, nominal: NominalPolicy | None = None, **kwargs: float) -> GoalTask:
    """The default task of a scene's system: a reach kind's own target (:class:`TargetTask`, with
    ``nominal`` if given), waypoints for cars, a goal for Air3D's evader, and for any other system (or
    whenever ``nominal`` is given) a :class:`NominalTask` with that policy."""
    if system.problem.reaches:
        if kwargs:
            raise ValueError(f"task options {sorted(kwargs)} do not apply to {system.name}'s own target")
        return TargetTask(system, nominal)
    if nominal is not None or not isinstance(system, (MultiVehicle, RelativePair)):
        if kwargs:
            raise ValueError(f"task options {sorted(kwargs)} need a goal task; {system.name} gets a NominalTask")
        return NominalTask(system, nominal)
    if isinstance(system, MultiVehicle):
        return WaypointTask(system, **kwargs)
    return EvaderGoalTask(system, **kwargs)
