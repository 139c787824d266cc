"""How an environment is drawn: the renderer a scene calls for, its frames and its trails.

Vehicle systems (those with ``car_poses``) of avoid problems are drawn as cars
(:class:`~reach_envs.rendering.SceneRenderer`), any other system (reach kinds included, whose goal
and obstacles live in the state space, not around a car) as a projection on two state
dimensions (:class:`~reach_envs.projection.ProjectionRenderer`, which shades the scene's regions:
failure set, goal, obstacles); :func:`render_frame` and
:func:`trail_points` hide the difference from the environments.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from reach.systems.arrays import FLOAT
from reach.systems.base import ControlAffineSystem
from reach_envs.projection import ProjectionRenderer, default_view_dims
from reach_envs.rendering import SceneRenderer
from reach_envs.scenes import Scene


def projected_view(scene: Scene) -> tuple[int, int] | None:
    """The two state dimensions a projection view draws, or ``None`` for an avoid vehicle system (drawn as cars)."""
    if _drawn_as_cars(scene.system):
        return None
    return scene.view_dims if scene.view_dims is not None else default_view_dims(scene.system)


def _drawn_as_cars(system: ControlAffineSystem) -> bool:
    """Cars for a vehicle system of an avoid problem; a reach kind's goal needs the projection view."""
    return hasattr(system, "car_poses") and not system.problem.reaches


def make_renderer(scene: Scene, size: int = 400) -> SceneRenderer | ProjectionRenderer:
    """The car renderer framing the scene's arena (or the cars' position domain) for vehicle systems,
    else the projection renderer on the scene's view dimensions."""
    system = scene.system
    view = projected_view(scene)
    if view is not None:
        title = scene.name if scene.name == system.name else f"{scene.name} ({system.name})"
        return ProjectionRenderer(system, view, title=title, size=size, regions=scene.regions)
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
