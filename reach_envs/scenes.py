"""Declarative scenes: what one simulation contains, and nothing more.

A :class:`Scene` names a system (or a list of cars from which a :class:`MultiVehicle` system is
built), how initial states are drawn, who drives the disturbance, and which effects are on:
process noise, collision termination, arena bounds, trails and the projection view of systems that
are not cars. Environments build their step from the active effects only: no disturbance policy is
evaluated without a disturbance, no random number is drawn without noise or a random policy, no
trail is recorded unless asked for and rendered.

A scene of a reach or reach-avoid system carries its goal and obstacles (:attr:`Scene.goal`,
:attr:`Scene.obstacles`, :attr:`Scene.regions`), derived from the system's target and constraint
margins (:mod:`reach_envs.regions`), never declared a second time.

Named scenes (:data:`SCENES`, :func:`make_scene`): ``air3d``, ``pursuit-evasion-6d``,
``three-car-9d``, ``four-car-12d``, ``five-car-15d``, ``quadrotor``, ``head-on``, ``crossing``,
``three-car-merge`` and ``three-car-crossing``. A scene
of any other system (an instance, a registered name or an import path ``pkg.mod:Class``):
:func:`system_scene`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from reach.integrators import INTEGRATORS
from reach.systems import (
    FLOAT,
    Air3D,
    Car,
    ControlAffineSystem,
    MultiVehicle,
    MultiVehicle6D,
    MultiVehicle9D,
    MultiVehicle12D,
    MultiVehicle15D,
    Quadrotor,
    make_system,
)
from reach.validation import check_known_fields
from reach_envs.policies import DISTURBANCE_KINDS, make_disturbance_policy
from reach_envs.regions import Region, goal_region, obstacle_region, system_regions


# ---------------------------------------------------------------------- initial states
@dataclass(frozen=True)
class UniformSafe:
    """States uniform over the system's domain, redrawn while the episode would already be decided:
    avoid, while ``l(x) <= margin`` (in collision); reach kinds, while in the goal (``l(x) <= 0``) or,
    reach-avoid, while ``g(x) <= margin`` (in an obstacle).

    ``unit_norm``: state dimensions rescaled to a unit vector after each draw, before it is judged:
    a quaternion's, ``(3, 4, 5, 6)`` of the quadrotor (a draw from its domain box is an attitude only
    once normalised)."""

    margin: float = 0.0
    max_tries: int = 10_000
    unit_norm: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        dims = tuple(self.unit_norm)
        if len(dims) == 1 or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in dims):
            raise ValueError(f"UniformSafe: unit_norm must be two or more state dimensions, got {self.unit_norm!r}")
        object.__setattr__(self, "unit_norm", dims)

    def sample(self, system: ControlAffineSystem, rng: np.random.Generator) -> np.ndarray:
        accept = _undecided(system, self.margin)
        dims = list(self.unit_norm)
        if dims and max(dims) >= system.state_dim:
            raise ValueError(f"UniformSafe: unit_norm {self.unit_norm} names a dimension {system.name} does not have")
        for _ in range(self.max_tries):
            x = system.sample_states_numpy(rng)
            if dims:
                norm = float(np.linalg.norm(x[dims]))
                if norm == 0.0:
                    continue
                x[dims] = x[dims] / norm
            if accept(x.tolist()):
                return x
        wanted = {"avoid": f"l(x) > {self.margin}", "reach": "l(x) > 0"}.get(
            system.kind, f"l(x) > 0 and g(x) > {self.margin}"
        )
        raise RuntimeError(
            f"UniformSafe: no state with {wanted} in {self.max_tries} draws from the {system.name} domain"
        )


def _undecided(system: ControlAffineSystem, margin: float) -> Callable[[list[float]], bool]:
    """``state -> bool``: whether an episode from the state is not decided yet (see :class:`UniformSafe`)."""
    if not system.problem.reaches:
        return lambda x: system.failure_margin_float(x) > margin
    if not system.problem.has_constraint:
        return lambda x: system.target_margin_columns(x, FLOAT) > 0.0
    return lambda x: (
        system.target_margin_columns(x, FLOAT) > 0.0 and system.constraint_margin_columns(x, FLOAT) > margin
    )


@dataclass(frozen=True)
class FixedState:
    """A fixed state plus optional uniform jitter ``[-jitter, jitter]`` per dimension."""

    state: tuple[float, ...]
    jitter: float | tuple[float, ...] = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "state", tuple(float(v) for v in self.state))
        if not all(math.isfinite(v) for v in self.state):
            raise ValueError(f"FixedState: state must be finite, got {self.state}")
        jitter = np.broadcast_to(np.asarray(self.jitter, dtype=np.float64), (len(self.state),))
        if not (np.isfinite(jitter).all() and (jitter >= 0).all()):
            raise ValueError(f"FixedState: jitter must be finite and >= 0, got {self.jitter}")

    def sample(self, system: ControlAffineSystem, rng: np.random.Generator) -> np.ndarray:
        if len(self.state) != system.state_dim:
            raise ValueError(f"FixedState: state has {len(self.state)} entries, {system.name} needs {system.state_dim}")
        x = np.array(self.state)
        if np.any(np.asarray(self.jitter) > 0):
            j = np.broadcast_to(np.asarray(self.jitter, dtype=np.float64), x.shape)
            x = x + rng.uniform(-j, j)
        return x


class CallableSampler:
    """Adapts ``fn(rng) -> state`` to the sampler protocol."""

    def __init__(self, fn: Callable[[np.random.Generator], Any]) -> None:
        self.fn = fn

    def sample(self, system: ControlAffineSystem, rng: np.random.Generator) -> np.ndarray:
        return np.asarray(self.fn(rng), dtype=np.float64)


# ---------------------------------------------------------------------- the scene
def _positive(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"Scene: {name} must be a positive finite number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Scene:
    """One simulation's contents; invalid fields fail here, naming the field.

    Attributes:
        system: the dynamics (any :class:`ControlAffineSystem`).
        name: label used in renders and reprs.
        initial_state: sampler with ``sample(system, rng)``, a fixed state, or ``fn(rng) -> state``.
        disturbance: ``None`` (no policy; the disturbance sits at its box centre), ``"pursue"``,
            ``"random"``, or a callable ``state -> disturbance`` in physical units.
        process_noise: ``None`` or the standard deviation per sqrt(second) of Brownian noise added
            to each state dimension (scalar or one per dimension).
        terminate_on_collision: end the episode when ``l(x) <= 0`` (avoid). A reach-kind episode
            always ends at its first collision (the goal counts only if reached before any), so
            ``False`` is refused there.
        arena: ``None`` or a half-width; a car leaving ``[-arena, arena]^2`` ends the episode.
        trails: record trails for rendering (only when a render mode is set): each car's position, or
            for a system without cars the projected state.
        horizon: episode length in seconds (default: the system's horizon).
        dt: step length in seconds.
        integrator: ``"rk4"`` or ``"euler"``.
        view_dims: for a system without cars, the two state dimensions (indices or state names) the
            projection view draws; ``None``: the first two non-periodic dimensions, else ``(0, 1)``.
            Vehicle systems of avoid problems are drawn as cars and take no ``view_dims``.
    """

    system: ControlAffineSystem
    name: str = "custom"
    initial_state: Any = field(default_factory=UniformSafe)
    disturbance: Any = None
    process_noise: float | tuple[float, ...] | None = None
    terminate_on_collision: bool = True
    arena: float | None = None
    trails: bool = False
    horizon: float | None = None
    dt: float = 0.02
    integrator: str = "rk4"
    view_dims: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.system, ControlAffineSystem):
            raise ValueError(f"Scene: system must be a ControlAffineSystem, got {type(self.system).__name__}")
        _positive("dt", self.dt)
        if self.system.problem.reaches and not (
            self.terminate_on_collision is True or self.terminate_on_collision is np.True_
        ):
            raise ValueError(
                f"Scene: terminate_on_collision must be True for a {self.system.kind} system (its episodes "
                f"end at the first collision), got {self.terminate_on_collision!r}"
            )
        if self.horizon is not None:
            _positive("horizon", self.horizon)
        if self.dt > self.episode_horizon:
            raise ValueError(f"Scene: dt ({self.dt}) must not exceed the horizon ({self.episode_horizon})")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"Scene: integrator must be one of {INTEGRATORS}, got {self.integrator!r}")
        if self.arena is not None:
            _positive("arena", self.arena)
            if not hasattr(self.system, "car_poses"):
                raise ValueError(f"Scene: arena needs a vehicle system, {self.system.name} has no cars")
        if self.process_noise is not None:
            noise = np.asarray(self.process_noise, dtype=np.float64)
            if noise.ndim > 1 or (noise.ndim == 1 and noise.shape[0] != self.system.state_dim):
                raise ValueError(
                    f"Scene: process_noise must be a scalar or have {self.system.state_dim} entries, "
                    f"got {self.process_noise!r}"
                )
            if not (np.isfinite(noise).all() and (noise >= 0).all()):
                raise ValueError(f"Scene: process_noise must be finite and >= 0, got {self.process_noise!r}")
        if isinstance(self.disturbance, str) and self.disturbance not in (*DISTURBANCE_KINDS, "none"):
            raise ValueError(
                f"Scene: disturbance must be None, one of {DISTURBANCE_KINDS} or a callable, got {self.disturbance!r}"
            )
        try:
            make_disturbance_policy(self.system, self.disturbance)
        except ValueError as err:
            raise ValueError(f"Scene: {err}") from None
        if self.view_dims is not None:
            object.__setattr__(self, "view_dims", _view_dims(self.system, self.view_dims))
        if not (hasattr(self.initial_state, "sample") or callable(self.initial_state)):
            try:
                object.__setattr__(
                    self, "initial_state", FixedState(tuple(np.asarray(self.initial_state, dtype=np.float64)))
                )
            except (TypeError, ValueError) as err:
                raise ValueError(f"Scene: initial_state must be a sampler, a state or a callable: {err}") from None
        if isinstance(self.initial_state, FixedState) and len(self.initial_state.state) != self.system.state_dim:
            raise ValueError(
                f"Scene: initial_state has {len(self.initial_state.state)} entries, "
                f"{self.system.name} has {self.system.state_dim} state dimensions"
            )

    @classmethod
    def from_cars(cls, cars: Sequence[Car | dict], collision_radius: float = 0.25, **kwargs: Any) -> Scene:
        """A scene of Dubins cars (speeds, turn bounds and roles) in a :class:`MultiVehicle` system."""
        if not cars:
            raise ValueError("Scene: cars must not be empty")
        horizon = kwargs.get("horizon") or 1.0
        system = MultiVehicle(cars, collision_radius=collision_radius, horizon=horizon)
        return cls(system=system, **kwargs)

    def replace(self, **changes: Any) -> Scene:
        """A copy with some fields changed (validated again)."""
        _check_fields(changes)
        return dataclasses.replace(self, **changes)

    @property
    def kind(self) -> str:
        """The system's kind of problem: ``"avoid"``, ``"reach"`` or ``"reach-avoid"``."""
        return self.system.kind

    @property
    def goal(self) -> Region | None:
        """The goal of a reach kind, ``{l <= 0}`` of the system's target margin; ``None`` for avoid."""
        return goal_region(self.system)

    @property
    def obstacles(self) -> Region | None:
        """The obstacles of a reach-avoid system, ``{g <= 0}`` of its constraint margin; else ``None``."""
        return obstacle_region(self.system)

    @property
    def regions(self) -> tuple[Region, ...]:
        """The sets an episode is judged by, in drawing order: the failure set (avoid), the goal
        (reach), the goal then the obstacles (reach-avoid)."""
        return system_regions(self.system)

    @property
    def episode_horizon(self) -> float:
        return self.horizon if self.horizon is not None else self.system.horizon

    @property
    def max_steps(self) -> int:
        """Steps per episode: ``ceil(horizon / dt)``, robust to round-off (1.1 / 0.02 gives 55)."""
        return max(1, math.ceil(self.episode_horizon / self.dt - 1e-9))

    def sampler(self) -> Any:
        return self.initial_state if hasattr(self.initial_state, "sample") else CallableSampler(self.initial_state)


def _check_fields(fields: dict[str, Any]) -> None:
    """``ValueError`` naming the keys of ``fields`` that are not :class:`Scene` fields."""
    check_known_fields(Scene, fields, "Scene")


def _view_dims(system: ControlAffineSystem, dims: Any) -> tuple[int, int]:
    """``view_dims`` checked and as two indices (state names are looked up)."""
    if hasattr(system, "car_poses") and not system.problem.reaches:
        raise ValueError(
            f"Scene: view_dims is for the projection view of systems without cars; {system.name} is drawn as cars"
        )
    names = system.state_names
    if isinstance(dims, (str, bytes)) or not isinstance(dims, Sequence) or len(dims) != 2:
        raise ValueError(f"Scene: view_dims must be a pair of state dimensions (indices or names), got {dims!r}")
    out = []
    for d in dims:
        if isinstance(d, str) and d in names:
            d = names.index(d)
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or not 0 <= d < len(names):
            raise ValueError(
                f"Scene: view_dims entry {d!r} is not a state dimension of {system.name}: "
                f"indices 0..{len(names) - 1} or names {list(names)}"
            )
        out.append(int(d))
    if out[0] == out[1]:
        raise ValueError(f"Scene: view_dims must name two different dimensions, got {dims!r}")
    return out[0], out[1]


def system_scene(system: Any, **fields: Any) -> Scene:
    """A scene of any system: an instance, a registered name or an import path ``pkg.mod:Class``
    (resolved by :func:`reach.systems.make_system`), named after the system unless ``name`` is given.

    ``fields`` are :class:`Scene` fields (``dt``, ``disturbance``, ``initial_state``, ``process_noise``,
    ``horizon``, ``view_dims``, ...); unknown ones raise ``ValueError`` naming them."""
    if isinstance(system, Scene):
        raise ValueError("system must be a system (an instance, a registered name or an import path), got a Scene")
    instance = make_system(system)
    _check_fields(fields)
    fields.setdefault("name", instance.name)
    return Scene(system=instance, **fields)


# ---------------------------------------------------------------------- named scenes
def _cars(n: int, speed: float = 0.6, max_turn_rate: float = 1.1) -> list[Car]:
    return [Car(speed, max_turn_rate, "control", f"car_{i + 1}") for i in range(n)]


def _poses_state(poses: Sequence[tuple[float, float, float]]) -> tuple[float, ...]:
    """Car poses (x, y, heading) to the MultiVehicle state order (positions, then headings)."""
    return tuple(v for x, y, _ in poses for v in (x, y)) + tuple(th for _, _, th in poses)


def _jitter(n: int, position: float = 0.05, heading: float = 0.1) -> tuple[float, ...]:
    return (position,) * (2 * n) + (heading,) * n


def _scene_air3d() -> Scene:
    return Scene(system=Air3D(), name="air3d", disturbance="pursue")


def _scene_pursuit_evasion_6d() -> Scene:
    return Scene(system=MultiVehicle6D(), name="pursuit-evasion-6d", disturbance="pursue")


def _scene_three_car_9d() -> Scene:
    return Scene(system=MultiVehicle9D(), name="three-car-9d")


def _scene_four_car_12d() -> Scene:
    return Scene(system=MultiVehicle12D(), name="four-car-12d")


def _scene_five_car_15d() -> Scene:
    return Scene(system=MultiVehicle15D(), name="five-car-15d")


def _scene_quadrotor() -> Scene:
    """Steps of 0.01 s (its body rates turn fast: at 0.02 s RK4 lets the quaternion's norm drift by a
    few per cent over a random episode, at 0.01 s by 1e-4) from unit quaternions."""
    return Scene(system=Quadrotor(), name="quadrotor", dt=0.01, initial_state=UniformSafe(unit_norm=(3, 4, 5, 6)))


def _scene_head_on() -> Scene:
    state = _poses_state([(-0.8, 0.0, 0.0), (0.8, 0.0, math.pi)])
    return Scene.from_cars(
        _cars(2), name="head-on", initial_state=FixedState(state, _jitter(2)), horizon=2.0, arena=1.5, trails=True
    )


def _scene_crossing() -> Scene:
    state = _poses_state([(-0.8, 0.0, 0.0), (0.0, -0.8, math.pi / 2)])
    return Scene.from_cars(
        _cars(2), name="crossing", initial_state=FixedState(state, _jitter(2)), horizon=2.0, arena=1.5, trails=True
    )


def _scene_three_car_merge() -> Scene:
    angles = [math.pi / 2, math.pi / 2 + 2 * math.pi / 3, math.pi / 2 + 4 * math.pi / 3]
    poses = [(0.8 * math.cos(a), 0.8 * math.sin(a), math.remainder(a + math.pi, 2 * math.pi)) for a in angles]
    return Scene.from_cars(
        _cars(3),
        name="three-car-merge",
        initial_state=FixedState(_poses_state(poses), _jitter(3)),
        horizon=2.0,
        arena=1.5,
        trails=True,
    )


def _scene_three_car_crossing() -> Scene:
    poses = [(-0.8, -0.1, 0.0), (0.1, -0.8, math.pi / 2), (0.8, 0.1, math.pi)]
    return Scene.from_cars(
        _cars(3),
        name="three-car-crossing",
        initial_state=FixedState(_poses_state(poses), _jitter(3)),
        horizon=2.0,
        arena=1.5,
        trails=True,
    )


#: Named scenes: name -> factory.
SCENES: dict[str, Callable[[], Scene]] = {
    "air3d": _scene_air3d,
    "pursuit-evasion-6d": _scene_pursuit_evasion_6d,
    "three-car-9d": _scene_three_car_9d,
    "four-car-12d": _scene_four_car_12d,
    "five-car-15d": _scene_five_car_15d,
    "quadrotor": _scene_quadrotor,
    "head-on": _scene_head_on,
    "crossing": _scene_crossing,
    "three-car-merge": _scene_three_car_merge,
    "three-car-crossing": _scene_three_car_crossing,
}


def make_scene(scene: str | Scene, **overrides: Any) -> Scene:
    """A named scene (or a given one) with some fields overridden, e.g. ``make_scene("air3d", dt=0.01)``."""
    if isinstance(scene, str):
        if scene not in SCENES:
            raise ValueError(f"unknown scene {scene!r}; named scenes: {sorted(SCENES)}")
        scene = SCENES[scene]()
    elif not isinstance(scene, Scene):
        raise ValueError(f"scene must be a Scene or a scene name, got {type(scene).__name__}")
    return scene.replace(**overrides) if overrides else scene


def env_scene(scene: str | Scene | None = None, system: Any = None, **overrides: Any) -> Scene:
    """The scene of an environment made from ``scene`` (:func:`make_scene`) or from ``system``
    (:func:`system_scene`) with field overrides: exactly one of the two, else ``ValueError``."""
    if scene is not None and system is not None:
        given = repr(scene) if isinstance(scene, str) else type(scene).__name__
        raise ValueError(f"give a scene or a system, not both (got scene {given} and system {system!r})")
    if system is not None:
        return system_scene(system, **overrides)
    if scene is None:
        raise ValueError(
            "no system or scene given: pass system=... (an instance, a registered name or an import path "
            f"'pkg.mod:Class', e.g. gym.make('Reach-v0', system=...)) or a scene (a Scene or one of {sorted(SCENES)})"
        )
    return make_scene(scene, **overrides)
