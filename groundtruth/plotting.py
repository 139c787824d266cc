"""Zero-level slices of a grid solution (matplotlib, Agg, written atomically as PNG)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from groundtruth.solution import GridSolution
from reach.atomic import atomic_path


def default_slice_values(solution: GridSolution) -> list[float]:
    """Values of the third dimension to slice at: four headings for a periodic one, else 4 evenly spaced."""
    g = solution.grid
    if g.ndim < 3:
        return [0.0]
    if g.periodic[2]:
        return [-math.pi / 2, 0.0, math.pi / 2, math.pi - 1e-9]
    return list(np.linspace(g.low[2], g.high[2], 6)[1:-1])


def plot_zero_level_slices(
    solution: GridSolution, path: str | os.PathLike, slice_values: Sequence[float] | None = None
) -> Path:
    """One panel per slice of dimension 3 (nearest node), axes = dimensions 1 and 2, one zero-level
    contour per stored time; a fourth dimension is held at its middle node."""
    # lazy: matplotlib only when drawing
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    g = solution.grid
    names = solution.system.state_names
    values = solution.values.numpy()
    slices = list(slice_values) if slice_values is not None else default_slice_values(solution)
    ax0 = solution.grid.axis(0).numpy()
    ax1 = solution.grid.axis(1).numpy()
    fig = Figure(figsize=(3.4 * len(slices), 3.5), dpi=110)
    FigureCanvasAgg(fig)
    colours = [f"C{i}" for i in range(len(solution.times))]
    for k, s in enumerate(slices):
        ax = fig.add_subplot(1, len(slices), k + 1)
        title = solution.system.name
        index: tuple = (slice(None), slice(None))
        if g.ndim >= 3:
            axis2 = solution.grid.axis(2).numpy()
            j = int(np.argmin(np.abs(np.angle(np.exp(1j * (axis2 - s)))) if g.periodic[2] else np.abs(axis2 - s)))
            index = (*index, j)
            title = f"{names[2]} = {axis2[j]:.3f}"
        if g.ndim == 4:
            index = (*index, g.shape[3] // 2)
        for t_i, t in enumerate(solution.times.tolist()):
            field = values[(t_i, *index)]
            ax.contour(ax0, ax1, field.T, levels=[0.0], colors=colours[t_i], linewidths=1.2)
            ax.plot([], [], color=colours[t_i], label=f"t = {t:g}")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        if k == 0:
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(
        f"{solution.system.name}: zero level of V (BRT boundary), grid {'x'.join(map(str, g.shape))}", fontsize=10
    )
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)
