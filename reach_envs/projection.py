"""Projection view: any system drawn on two of its state dimensions (matplotlib Agg, no pyplot state).

Systems that are not cars (no ``car_poses``) are drawn this way: the axes span the domain of the two
dimensions the scene's ``view_dims`` chooses (default: the first two non-periodic dimensions, else
``(0, 1)``) and carry their state names; the scene's regions (:mod:`reach_envs.regions`: the failure
set ``{l <= 0}`` of an avoid system, the goal ``{l <= 0}`` of a reach kind in green and the obstacles
``{g <= 0}`` of a reach-avoid one in the failure set's red, over the goal) are shaded on a ``96 x 96``
grid over those two dimensions with the other dimensions held at the current state (one batched
margin call per region on the NumPy backend, redone only when the held values change); the
current state is a marker (grey after a collision), an optional trail follows the projected states
(broken where a periodic dimension wraps), and the time and the held values sit in the corners.
Frames have the car renderer's size; the figure is created on the first frame and updated in place.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from reach.systems.arrays import NUMPY, Backend, Column
from reach.systems.base import ControlAffineSystem
from reach_envs.regions import FAILURE_SET, GOAL, OBSTACLES, Region, system_regions
from reach_envs.rendering import CRASHED_COLOUR, ROLE_COLOURS

#: RGB of the shaded failure set (opaque, so frames can be searched for it).
FAILURE_RGB = (244, 166, 166)
#: RGB of a reach kind's shaded goal (opaque, as the failure set)
GOAL_RGB = (160, 216, 160)
#: RGB of a reach-avoid system's obstacles: they are its failure set, and look it
OBSTACLE_RGB = FAILURE_RGB
#: the colour of each region, by :attr:`~reach_envs.regions.Region.name`
REGION_RGB = {FAILURE_SET: FAILURE_RGB, GOAL: GOAL_RGB, OBSTACLES: OBSTACLE_RGB}
#: grid points per axis on which ``l`` is evaluated
GRID = 96


def default_view_dims(system: ControlAffineSystem) -> tuple[int, int]:
    """The system's own view (:meth:`~reach.systems.base.ControlAffineSystem.view_dims`: the first two
    non-periodic state dimensions, else ``(0, 1)``, unless the system overrides it)."""
    if system.state_dim < 2:
        raise ValueError(f"a projection view needs two state dimensions; {system.name} has {system.state_dim}")
    return system.view_dims()


class ProjectionRenderer:
    """Draws states of ``system`` projected on ``dims`` into ``(size, size, 3)`` uint8 frames.

    ``regions`` are the sets to shade, in drawing order (default: the system's own,
    :func:`~reach_envs.regions.system_regions`; a scene passes :attr:`~reach_envs.scenes.Scene.regions`).
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        dims: tuple[int, int],
        title: str = "",
        size: int = 400,
        grid: int = GRID,
        regions: Sequence[Region] | None = None,
    ) -> None:
        # lazy: matplotlib only when drawing
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        i, j = dims
        self.system = system
        self.dims = (int(i), int(j))
        self.size = int(size)
        self._held_dims = [k for k in range(system.state_dim) if k not in self.dims]
        self._periodic = [system.periodic[i], system.periodic[j]]
        (x0, x1), (y0, y1) = system.domain[i], system.domain[j]
        xs = np.linspace(x0, x1, grid)
        ys = np.linspace(y0, y1, grid)
        self._gx, self._gy = np.meshgrid(xs, ys)  # rows follow dims[1], columns dims[0]
        self._regions = tuple(system_regions(system) if regions is None else regions)
        unknown = [r.name for r in self._regions if r.name not in REGION_RGB]
        if unknown:
            raise ValueError(f"ProjectionRenderer: no colour for region(s) {unknown}; regions are {list(REGION_RGB)}")
        self._rgba = np.zeros((grid, grid, 4), dtype=np.uint8)
        self._held: tuple[float, ...] | None = None

        dpi = 100
        self.figure = Figure(figsize=(self.size / dpi, self.size / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.figure)
        ax = self.figure.add_axes((0.13, 0.11, 0.83, 0.81))
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_xlabel(system.state_names[i], fontsize=8)
        ax.set_ylabel(system.state_names[j], fontsize=8)
        ax.grid(True, linewidth=0.3, alpha=0.5)
        ax.set_axisbelow(True)
        ax.tick_params(labelsize=7)
        if title:
            ax.set_title(title, fontsize=9)
        self.axes = ax
        self.image = ax.imshow(
            self._rgba, origin="lower", extent=(x0, x1, y0, y1), interpolation="nearest", aspect="auto", zorder=0
        )
        colour = ROLE_COLOURS["control"]
        (self.trail,) = ax.plot([], [], color=colour, linewidth=1.0, alpha=0.6)
        (self.marker,) = ax.plot([], [], "o", markersize=7, color=colour, markeredgecolor="black", markeredgewidth=0.5)
        self.clock = ax.text(0.02, 0.97, "", transform=ax.transAxes, fontsize=8, va="top", family="monospace")
        self.slice = ax.text(0.02, 0.02, "", transform=ax.transAxes, fontsize=7, va="bottom", family="monospace")

    def failure_mask(self, state: Sequence[float]) -> np.ndarray:
        """``(grid, grid)`` bools, ``l <= 0`` over the view with the other dimensions at ``state``
        (rows follow ``dims[1]``, columns ``dims[0]``): one batched call, no loop over grid points."""
        return self.margin_mask(self.system.failure_margin_columns, state)

    def margin_mask(
        self, margin_columns: Callable[[Sequence[Column], Backend], Column], state: Sequence[float]
    ) -> np.ndarray:
        """``(grid, grid)`` bools, ``margin <= 0`` over the view with the other dimensions at ``state``
        (rows follow ``dims[1]``, columns ``dims[0]``) for any margin (a region's): one batched call."""
        shape = self._gx.shape
        columns = [np.full(shape, float(v)) for v in state]
        columns[self.dims[0]] = self._gx
        columns[self.dims[1]] = self._gy
        margin = np.asarray(margin_columns(columns, NUMPY), dtype=np.float64)
        return np.broadcast_to(margin, shape) <= 0.0

    def _trail_xy(self, points: Sequence[tuple[float, float]]) -> np.ndarray:
        """Trail points ``(k, 2)``, with a NaN row wherever a periodic dimension wrapped."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if len(pts) > 1 and any(self._periodic):
            jump = np.zeros(len(pts) - 1, dtype=bool)
            for c, periodic in enumerate(self._periodic):
                if periodic:
                    jump |= np.abs(np.diff(pts[:, c])) > math.pi
            if jump.any():
                pts = np.insert(pts, np.flatnonzero(jump) + 1, np.nan, axis=0)
        return pts

    def render(
        self,
        state: Sequence[float],
        time: float,
        trails: Sequence[Sequence[tuple[float, float]]] | None = None,
        crashed: bool = False,
    ) -> np.ndarray:
        """One frame: the state, elapsed ``time``, an optional trail (``trails[0]``, projected points)."""
        held = tuple(float(state[k]) for k in self._held_dims)
        if held != self._held:
            self._rgba[...] = 0  # transparent, then each region over the ones before it
            for region in self._regions:
                self._rgba[self.margin_mask(region.margin_columns, state)] = (*REGION_RGB[region.name], 255)
            self.image.set_data(self._rgba.copy())
            names = self.system.state_names
            self.slice.set_text("  ".join(f"{names[k]}={v:.2f}" for k, v in zip(self._held_dims, held)))
            self._held = held
        i, j = self.dims
        self.marker.set_data([float(state[i])], [float(state[j])])
        self.marker.set_markerfacecolor(CRASHED_COLOUR if crashed else ROLE_COLOURS["control"])
        if trails and len(trails[0]):
            pts = self._trail_xy(trails[0])
            self.trail.set_data(pts[:, 0], pts[:, 1])
        else:
            self.trail.set_data([], [])
        self.clock.set_text(f"t = {time:5.2f} s")
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.figure.clear()
