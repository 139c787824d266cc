"""Uniform Cartesian grids over a system's domain, with periodic dimensions.

Along a periodic dimension of period ``P = high - low`` the ``N`` nodes are ``low + k P / N``
(``k = 0 .. N-1``; ``high`` itself is the same point as ``low``), as the MATLAB level-set toolbox
places them. Along other dimensions the nodes are ``linspace(low, high, N)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from reach.systems.base import ControlAffineSystem


@dataclass(frozen=True)
class Grid:
    """Node layout of a uniform grid; coordinates are built on demand in any dtype and device."""

    low: tuple[float, ...]
    high: tuple[float, ...]
    shape: tuple[int, ...]
    periodic: tuple[bool, ...]

    def __post_init__(self) -> None:
        n = len(self.shape)
        if not (len(self.low) == len(self.high) == len(self.periodic) == n):
            raise ValueError(f"Grid: low, high, shape and periodic must have equal lengths, got {self}")
        for i, (lo, hi, m) in enumerate(zip(self.low, self.high, self.shape)):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"Grid: dimension {i} needs finite low < high, got [{lo}, {hi}]")
            if isinstance(m, bool) or not isinstance(m, int) or m < 5:
                raise ValueError(f"Grid: dimension {i} needs at least 5 nodes (WENO5 stencil), got {m!r}")

    @classmethod
    def for_system(cls, system: ControlAffineSystem, shape: int | Sequence[int]) -> Grid:
        """A grid over the system's domain with ``shape`` nodes (an int means the same in every dimension)."""
        n = system.state_dim
        dims = (shape,) * n if isinstance(shape, int) else tuple(shape)
        if len(dims) != n:
            raise ValueError(f"Grid: {system.name} has {n} dimensions, got shape {dims}")
        return cls(
            tuple(float(lo) for lo, _ in system.domain),
            tuple(float(hi) for _, hi in system.domain),
            tuple(int(m) for m in dims),
            tuple(bool(p) for p in system.periodic),
        )

    def widened(self, box: Sequence[tuple[float, float]]) -> tuple[Grid, tuple[slice, ...]]:
        """This grid with whole nodes of its own spacing added along each non-periodic dimension until
        it covers ``box``, and the slices that cut this grid's nodes back out of the wider one.

        The solver solves a system's domain on the wider grid when the system's
        :meth:`~reach.systems.base.ControlAffineSystem.training_domain` is wider: trajectories that
        leave the domain there before their margin decides them get their values from the wider
        grid's nodes instead of from the edge's extrapolated ghost nodes."""
        if len(box) != self.ndim:
            raise ValueError(f"Grid: box has {len(box)} dimensions, the grid {self.ndim}")
        low, high, shape, keep = [], [], [], []
        for lo, hi, m, p, dx, (b_lo, b_hi) in zip(self.low, self.high, self.shape, self.periodic, self.spacing, box):
            before = 0 if p else max(0, math.ceil((lo - b_lo) / dx - 1e-9))
            after = 0 if p else max(0, math.ceil((b_hi - hi) / dx - 1e-9))
            low.append(lo - before * dx)
            high.append(hi + after * dx)
            shape.append(m + before + after)
            keep.append(slice(before, before + m))
        return Grid(tuple(low), tuple(high), tuple(shape), self.periodic), tuple(keep)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def spacing(self) -> tuple[float, ...]:
        return tuple(
            (hi - lo) / (m if p else m - 1) for lo, hi, m, p in zip(self.low, self.high, self.shape, self.periodic)
        )

    @property
    def num_points(self) -> int:
        return math.prod(self.shape)

    def axis(self, i: int, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> torch.Tensor:
        """Node coordinates along dimension ``i``."""
        k = torch.arange(self.shape[i], dtype=torch.float64)
        return (self.low[i] + k * self.spacing[i]).to(dtype=dtype, device=device)

    def columns(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> list[torch.Tensor]:
        """One broadcastable coordinate tensor per dimension (shape 1 except along its own axis).

        Physics on columns broadcasts, so functions of a single coordinate (``cos x3``) are computed
        on one axis instead of the whole grid.
        """
        cols = []
        for i in range(self.ndim):
            view = [1] * self.ndim
            view[i] = self.shape[i]
            cols.append(self.axis(i, dtype, device).reshape(view))
        return cols

    def points(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
        """All nodes as a ``(*shape, ndim)`` tensor."""
        axes = [self.axis(i, dtype, device) for i in range(self.ndim)]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
