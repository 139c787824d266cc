"""RGB frames of a fleet, drawn with matplotlib's Agg backend in the style of :mod:`reach_envs.rendering`.

Each car is an oriented triangle with its dashed collision circle of radius R, each goal a cross of
the car's colour; a crashed car stays grey where it stopped, an arrived car (and its goal) is no
longer drawn, and the title carries the time and the number of cars still driving. Every kind of
mark is one matplotlib collection, updated in place, so a frame costs one figure draw whatever the
number of cars, and the figure of a scene is built once and reused (:func:`render_fleet` keeps a few).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import torch

from reach_envs.fleet_scenes import FleetScene
from reach_envs.rendering import CRASHED_COLOUR

#: pixels per side of a frame
FRAME_SIZE = 480


class FleetRenderer:
    """Draws one episode's fleet states of ``scene`` into ``(size, size, 3)`` uint8 frames."""

    def __init__(self, scene: FleetScene, size: int = FRAME_SIZE) -> None:
        # lazy: matplotlib only when drawing
        from matplotlib import colormaps
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.collections import EllipseCollection, PolyCollection
        from matplotlib.colors import to_rgba
        from matplotlib.figure import Figure

        self.scene = scene
        self.n = scene.n_cars
        self.size = int(size)
        dpi = 100
        self.figure = Figure(figsize=(self.size / dpi, self.size / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.figure)
        ax = self.figure.add_axes((0.08, 0.06, 0.88, 0.88))
        extent = scene.extent
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        ax.set_aspect("equal")
        ax.grid(True, linewidth=0.3, alpha=0.5)
        ax.tick_params(labelsize=7)
        self.title = f"{scene.layout}, {self.n} cars"
        self.clock = ax.set_title(self.title, fontsize=9, family="monospace")
        hsv = colormaps["hsv"]  # a hue wheel: no car shares the crashed grey
        self.colours = np.array([to_rgba(hsv(i / self.n)) for i in range(self.n)])
        self.crashed_colour = np.array(to_rgba(CRASHED_COLOUR))
        self.length = max(1.2 * scene.collision_radius, 0.02 * 2 * extent)
        r2 = 2.0 * scene.collision_radius
        zeros = np.zeros((self.n, 2))
        self.circles = EllipseCollection(
            r2, r2, 0.0, units="xy", offsets=zeros, offset_transform=ax.transData, facecolors="none",
            edgecolors=self.colours, linestyles="--", linewidths=0.6,
        )  # fmt: skip
        ax.add_collection(self.circles)
        self.cars = PolyCollection(
            np.zeros((self.n, 3, 2)), facecolors=self.colours, edgecolors="black", linewidths=0.4
        )
        ax.add_collection(self.cars)
        self.goal_marks = ax.scatter(
            np.zeros(self.n), np.zeros(self.n), marker="x", s=22, c=self.colours, linewidths=1.2
        )
        self._triangle = np.array([[1.0, 0.0], [-0.6, 0.5], [-0.6, -0.5]]) * self.length

    def render(
        self,
        x: Any,
        goals: Any,
        present: Any,
        time: float | None = None,
        crashed: Any = None,
    ) -> np.ndarray:
        """One frame: state ``(3N,)``, goals ``(N, 2)``, presence ``(N,)`` (NumPy, torch or lists);
        ``crashed`` ``(N,)`` marks absent cars that collided (drawn grey; other absent cars are hidden)."""
        n = self.n
        state = _array("x", x, (3 * n,))
        goal = _array("goals", goals, (n, 2))
        here = _array("present", present, (n,), kind="b")
        hit = np.zeros(n, dtype=bool) if crashed is None else _array("crashed", crashed, (n,), kind="b")
        shown = here | hit
        pos, th = state[: 2 * n].reshape(n, 2), state[2 * n :]
        c, s = np.cos(th), np.sin(th)
        rot = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], 1)  # (N, 2, 2): row vectors times rot
        tri = np.einsum("kj,njl->nkl", self._triangle, rot) + pos[:, None, :]
        colours = np.where(hit[:, None] & ~here[:, None], self.crashed_colour, self.colours)
        self.cars.set_verts(tri[shown])
        self.cars.set_facecolors(colours[shown])
        self.circles.set_offsets(pos[shown])
        self.circles.set_edgecolors(colours[shown])
        self.goal_marks.set_offsets(goal[here])
        self.goal_marks.set_color(self.colours[here])
        clock = "" if time is None else f", t = {time:6.2f} s, {int(here.sum())} left"
        self.clock.set_text(self.title + clock)
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.figure.clear()


def _array(what: str, value: Any, shape: tuple[int, ...], kind: str = "f") -> np.ndarray:
    """``value`` (NumPy, torch, list) as an array of ``shape``: finite floats, or bools for ``kind="b"``."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    out = np.asarray(value)
    if out.shape != shape:
        raise ValueError(f"render_fleet: {what} must have shape {shape}, got {out.shape}")
    if kind == "b":
        if out.dtype != bool:
            raise ValueError(f"render_fleet: {what} must be bool, got {out.dtype}")
        return out
    if out.dtype.kind not in "iuf" or not np.isfinite(out).all():
        raise ValueError(f"render_fleet: {what} must be finite real numbers")
    return out.astype(np.float64)


@functools.lru_cache(maxsize=4)
def fleet_renderer(scene: FleetScene, size: int = FRAME_SIZE) -> FleetRenderer:
    """The (cached) renderer of ``scene``: its figure is built once for every frame drawn of it."""
    return FleetRenderer(scene, size)


def render_fleet(
    x: Any,
    goals: Any,
    present: Any,
    scene: FleetScene,
    time: float | None = None,
    crashed: Any = None,
) -> np.ndarray:
    """An RGB frame ``(480, 480, 3)`` uint8 of one episode's fleet: ``x`` ``(3N,)``, ``goals``
    ``(N, 2)``, ``present`` ``(N,)`` bool, optional ``time`` and ``crashed`` (absent cars drawn grey).

    For a batched rollout, pass one episode's row per frame, e.g. ``render_fleet(out.states[t, 0],
    goals[0], out.present[t, 0], scene, t * scene.dt, out.collided[0])`` over the recorded steps
    (:func:`reach_envs.fleet.rollout` with ``record=True``)."""
    if not isinstance(scene, FleetScene):
        raise ValueError(f"render_fleet: scene must be a FleetScene, got {type(scene).__name__}")
    if time is not None and not math.isfinite(time):
        raise ValueError(f"render_fleet: time must be finite, got {time!r}")
    return fleet_renderer(scene).render(x, goals, present, time, crashed)
