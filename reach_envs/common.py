"""Pieces every environment kind shares: spaces, action validation, renderer set-up, trails.

Rendering picks its view from the scene: vehicle systems (those with ``car_poses``) are drawn as cars
(:class:`~reach_envs.rendering.SceneRenderer`), any other system as a projection on two state
dimensions (:class:`~reach_envs.projection.ProjectionRenderer`); :func:`render_frame` and
:func:`trail_points` hide the difference from the environments.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import numpy as np
from gymnasium import spaces

from reach.systems.backend import FLOAT
from reach.systems.base import ControlAffineSystem
from reach_envs.projection import ProjectionRenderer, default_view_dims
from reach_envs.rendering import SceneRenderer
from reach_envs.scenes import Scene


def observation_space(system: ControlAffineSystem) -> spaces.Box:
    """float32 states: periodic dimensions (headings) in [-pi, pi], the others unbounded (states may
    leave the sampling domain: cars drive off it, process noise is unbounded)."""
    low = np.array([-np.pi if p else -np.inf for p in system.periodic], dtype=np.float32)
    return spaces.Box(low=low, high=-low, dtype=np.float32)


def action_space(dim: int) -> spaces.Box:
    """Controls (turn rates, ...) normalised to [-1, 1]: -1 and 1 are the ends of each control's box."""
    return spaces.Box(low=-1.0, high=1.0, shape=(dim,), dtype=np.float32)


def check_action(action: object, shape: tuple[int, ...]) -> np.ndarray:
    """``action`` as float64 of the given shape; wrong shapes and NaN/inf raise ``ValueError``.

    Out-of-range values are *not* an error: callers clip them to [-1, 1] (documented behaviour,
    as for any Box action space whose samples an agent may overshoot).
    """
    try:
        a = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"action must be numeric with shape {shape}, got {action!r}") from err
    if a.shape != shape:
        raise ValueError(f"action must have shape {shape}, got shape {a.shape}: {action!r}")
    if not (all(map(math.isfinite, a.tolist())) if a.ndim == 1 and a.size <= 8 else np.isfinite(a).all()):
        raise ValueError(f"action contains a non-finite value (NaN or inf): {action!r}")
    return a


def check_reset_options(options: object, allowed: tuple[str, ...], unknown_keys: str = "raise") -> dict:
    """``reset`` options as a dict; unknown keys raise ``ValueError`` (a misspelt ``"sate"`` would
    otherwise start from a random state without a word), or with ``unknown_keys="warn"`` warn.

    The PettingZoo env warns instead of raising: PettingZoo's own API test resets with the made-up
    ``options={"options": 1}`` to check that ``options`` is accepted, and an env must pass that test."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise ValueError(f"reset options must be a dict, got {type(options).__name__}")
    unknown = sorted(map(str, set(options) - set(allowed)))
    if unknown:
        message = f"unknown reset option(s) {unknown}; this environment takes {list(allowed)}"
        if unknown_keys == "warn":
            warnings.warn(message + " (ignored)", UserWarning, stacklevel=3)
        else:
            raise ValueError(message)
    return options


class EpisodeOverError(RuntimeError):
    """``step`` was called before ``reset`` or after the episode ended (terminated or truncated)."""


def check_state(state: object, system: ControlAffineSystem) -> np.ndarray:
    """A user-given initial state as float64 ``(n,)``; wrong shapes and NaN/inf raise ``ValueError``."""
    x = np.asarray(state, dtype=np.float64)
    if x.shape != (system.state_dim,):
        raise ValueError(f"state for {system.name} must have shape ({system.state_dim},), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"state contains a non-finite value (NaN or inf): {x.tolist()}")
    return x


def projected_view(scene: Scene) -> tuple[int, int] | None:
    """The two state dimensions a projection view draws, or ``None`` for a vehicle system (drawn as cars)."""
    if hasattr(scene.system, "car_poses"):
        return None
    return scene.view_dims if scene.view_dims is not None else default_view_dims(scene.system)


def make_renderer(scene: Scene, size: int = 400) -> SceneRenderer | ProjectionRenderer:
    """The car renderer framing the scene's arena (or the cars' position domain) for vehicle systems,
    else the projection renderer on the scene's view dimensions."""
    system = scene.system
    view = projected_view(scene)
    if view is not None:
        title = scene.name if scene.name == system.name else f"{scene.name} ({system.name})"
        return ProjectionRenderer(system, view, title=title, size=size)
    extent = scene.arena if scene.arena is not None else 1.15 * getattr(system, "half_width", 1.0)
    return SceneRenderer(
        roles=system.car_roles,
        names=system.car_names,
        collision_radius=system.collision_radius,
        half_extent=extent,
        title=f"{scene.name} ({system.name})",
        size=size,
    )


def render_frame(
    renderer: SceneRenderer | ProjectionRenderer,
    system: ControlAffineSystem,
    state: Sequence[float],
    time: float,
    trails: Sequence[Sequence[tuple[float, float]]] | None,
    crashed: bool,
) -> np.ndarray:
    """One frame of ``state`` (Python floats) with the renderer :func:`make_renderer` chose."""
    if isinstance(renderer, ProjectionRenderer):
        return renderer.render(state, time, trails, crashed)
    hit = [crashed and role == "control" for role in system.car_roles]
    return renderer.render(system.car_poses(state, FLOAT), time, trails, hit)


def trail_points(scene: Scene) -> Callable[[Sequence[float]], list[tuple[float, float]]]:
    """``state -> points`` that trails record: each car's position, or the state projected on the view."""
    view = projected_view(scene)
    if view is None:
        system = scene.system
        return lambda x: [(float(px), float(py)) for px, py, _ in system.car_poses(x, FLOAT)]
    i, j = view
    return lambda x: [(float(x[i]), float(x[j]))]
