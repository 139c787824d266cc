"""RGB frames of a scene drawn with matplotlib's Agg backend (no display, no pyplot state).

Cars are oriented triangles (blue: control, red: disturbance, grey: crashed), each control car
carries its dashed collision circle of radius R, optional trails follow the cars, and the elapsed
time sits in a corner. The figure is created once, on the first frame, and its artists are updated
in place for every later frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

ROLE_COLOURS = {"control": "#1f77b4", "disturbance": "#d62728"}
CRASHED_COLOUR = "#7f7f7f"


class SceneRenderer:
    """Draws car poses into ``(size, size, 3)`` uint8 frames."""

    def __init__(
        self,
        roles: Sequence[str],
        names: Sequence[str],
        collision_radius: float,
        half_extent: float,
        title: str = "",
        size: int = 400,
        car_length: float | None = None,
    ) -> None:
        # lazy: matplotlib only when drawing
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle, Polygon

        self.roles = tuple(roles)
        self.size = int(size)
        dpi = 100
        self.figure = Figure(figsize=(self.size / dpi, self.size / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.figure)
        ax = self.figure.add_axes((0.08, 0.08, 0.88, 0.84))
        ax.set_xlim(-half_extent, half_extent)
        ax.set_ylim(-half_extent, half_extent)
        ax.set_aspect("equal")
        ax.grid(True, linewidth=0.3, alpha=0.5)
        ax.tick_params(labelsize=7)
        if title:
            ax.set_title(title, fontsize=9)
        self.axes = ax
        self._length = car_length if car_length is not None else 0.06 * 2 * half_extent
        self.glyphs = []
        self.circles = []
        self.trails = []
        for role, name in zip(self.roles, names):
            colour = ROLE_COLOURS[role]
            glyph = Polygon(
                np.zeros((3, 2)), closed=True, facecolor=colour, edgecolor="black", linewidth=0.5, label=name
            )
            ax.add_patch(glyph)
            self.glyphs.append(glyph)
            circle = None
            if role == "control":
                circle = Circle(
                    (0.0, 0.0), collision_radius, fill=False, linestyle="--", edgecolor=colour, linewidth=0.8
                )
                ax.add_patch(circle)
            self.circles.append(circle)
            (trail,) = ax.plot([], [], color=colour, linewidth=1.0, alpha=0.6)
            self.trails.append(trail)
        self.clock = ax.text(0.02, 0.97, "", transform=ax.transAxes, fontsize=8, va="top", family="monospace")

    def _triangle(self, x: float, y: float, th: float) -> np.ndarray:
        L = self._length
        c, s = math.cos(th), math.sin(th)
        pts = np.array([[L, 0.0], [-0.6 * L, 0.5 * L], [-0.6 * L, -0.5 * L]])
        return pts @ np.array([[c, s], [-s, c]]) + np.array([x, y])

    def render(
        self,
        poses: Sequence[tuple[float, float, float]],
        time: float,
        trails: Sequence[Sequence[tuple[float, float]]] | None = None,
        crashed: Sequence[bool] | None = None,
    ) -> np.ndarray:
        """One frame: car poses ``(x, y, heading)``, elapsed ``time``, optional trails and crash flags."""
        for k, (x, y, th) in enumerate(poses):
            glyph = self.glyphs[k]
            glyph.set_xy(self._triangle(float(x), float(y), float(th)))
            hit = bool(crashed[k]) if crashed is not None else False
            glyph.set_facecolor(CRASHED_COLOUR if hit else ROLE_COLOURS[self.roles[k]])
            if self.circles[k] is not None:
                self.circles[k].center = (float(x), float(y))
            if trails is not None and len(trails[k]):
                xs, ys = zip(*trails[k])
                self.trails[k].set_data(xs, ys)
            else:
                self.trails[k].set_data([], [])
        self.clock.set_text(f"t = {time:5.2f} s")
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.figure.clear()
