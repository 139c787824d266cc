"""A grid solution of the HJI value function: interpolation, gradients, self-describing ``.npz`` files.

:class:`GridSolution` implements the value-function interface (``value(x, t)``, ``gradient(x, t)``,
batched, any device): multilinear interpolation in space (periodic-aware) and linear interpolation
between stored times. Gradients are central differences on the grid (one-sided at non-periodic
edges), interpolated the same way, so the optimal control from a grid solution is smooth enough for
closed-loop use.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from groundtruth.grid import Grid
from reach.atomic import atomic_path
from reach.provenance import package_versions
from reach.systems import ControlAffineSystem, system_from_config
from reach.validation import check_input_file
from reach.value_function import check_time

FORMAT = "reach.groundtruth.v1"


@dataclass
class GridSolution:
    """Values ``(len(times), *grid.shape)`` of a system on a grid at increasing times-to-go."""

    system: ControlAffineSystem
    grid: Grid
    times: torch.Tensor
    values: torch.Tensor
    metadata: dict[str, Any] = field(default_factory=dict)
    outside: Literal["error", "clamp"] = "error"

    def __post_init__(self) -> None:
        if self.values.shape != (len(self.times), *self.grid.shape):
            raise ValueError(f"values shape {tuple(self.values.shape)} != ({len(self.times)}, *{self.grid.shape})")
        if not torch.isfinite(self.values).all():
            raise ValueError("GridSolution: values contain NaN or inf")
        self._check_against_system()
        self._gradients: torch.Tensor | None = None
        self._cache: dict[tuple[str, torch.dtype, torch.device], torch.Tensor] = {}
        # each stored time-to-go's slice: a query at one of them reads that slice alone
        self._stored: dict[float, int] = {float(v): k for k, v in enumerate(self.times.tolist())}

    def _check_against_system(self) -> None:
        """Refuse a grid that contradicts its system, or times that cannot be interpolated: a wrong
        dimension, a dimension marked periodic that the system says is not (or the reverse: values
        would wrap around a boundary that is a wall), and times-to-go that are not finite,
        non-negative and strictly increasing (a duplicated time divides by zero, a descending one
        inverts every bracket)."""
        system = self.system
        if self.grid.ndim != system.state_dim:
            raise ValueError(f"GridSolution: a {self.grid.ndim}D grid for {system.name}, a {system.state_dim}D system")
        periodic = tuple(bool(p) for p in system.periodic)
        if tuple(self.grid.periodic) != periodic:
            raise ValueError(
                f"GridSolution: the grid's periodic dimensions {list(self.grid.periodic)} differ from "
                f"{system.name}'s {list(periodic)} (state names {list(system.state_names)})"
            )
        t = self.times
        if t.ndim != 1 or len(t) == 0:
            raise ValueError(f"GridSolution: times must be a non-empty 1-D list, got shape {tuple(t.shape)}")
        if not torch.isfinite(t).all() or bool((t < 0).any()):
            raise ValueError(f"GridSolution: times-to-go must be finite and >= 0, got {t.tolist()}")
        if len(t) > 1 and not bool((t[1:] > t[:-1]).all()):
            raise ValueError(f"GridSolution: times-to-go must be strictly increasing, got {t.tolist()}")

    @property
    def time_range(self) -> tuple[float, float]:
        """The stored times-to-go: values between them are interpolated, others refused."""
        return (float(self.times[0]), float(self.times[-1]))

    # ------------------------------------------------------------------ slices
    def at(self, t: float) -> torch.Tensor:
        """The value grid at a stored time ``t`` (exact match required)."""
        k = torch.nonzero(torch.isclose(self.times, torch.tensor(float(t), dtype=self.times.dtype), atol=1e-9))
        if k.numel() == 0:
            raise ValueError(f"time {t} is not stored; stored times: {self.times.tolist()}")
        return self.values[int(k[0])]

    def resampled(self, shape: int | tuple[int, ...]) -> GridSolution:
        """This solution interpolated onto a grid of ``shape`` nodes over the same box, at the same
        times: a smaller file of the same value function (the compact pair grid that ships with
        the package is the 101^3 solve resampled, ``benchmarks/pair_grid_resolution.py``).

        Resampling a fine solve keeps more of its accuracy at the coarse nodes than solving on the
        coarse grid, whose own truncation error is larger; the benchmark measures both."""
        dims = tuple(int(m) for m in shape) if isinstance(shape, tuple) else (int(shape),) * self.grid.ndim
        grid = Grid(self.grid.low, self.grid.high, dims, self.grid.periodic)
        nodes = grid.points(torch.float64).reshape(-1, grid.ndim)
        values = torch.stack([self.value(nodes, float(t)).reshape(grid.shape) for t in self.times])
        metadata = {**self.metadata, "resampled_from": list(self.grid.shape)}
        return GridSolution(self.system, grid, self.times.clone(), values.to(self.values.dtype), metadata, self.outside)

    # ------------------------------------------------------------------ interpolation
    def _table(self, kind: str, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        key = (kind, dtype, device)
        if key not in self._cache:
            if kind == "value":
                src = self.values
            elif kind == "gradient":
                src = self._grid_gradients()
            else:  # value and gradient side by side: one interpolation serves both
                src = torch.cat([self.values.unsqueeze(-1), self._grid_gradients()], dim=-1)
            self._cache[key] = src.to(dtype=dtype, device=device)
        return self._cache[key]

    def _grid_gradients(self) -> torch.Tensor:
        if self._gradients is None:
            v = self.values.double()
            grads = []
            for i, (dx, periodic) in enumerate(zip(self.grid.spacing, self.grid.periodic)):
                dim = i + 1
                if periodic:
                    g = (torch.roll(v, -1, dim) - torch.roll(v, 1, dim)) / (2 * dx)
                else:
                    g = torch.gradient(v, spacing=dx, dim=dim, edge_order=2)[0]
                grads.append(g)
            self._gradients = torch.stack(grads, dim=-1).to(self.values.dtype)
        return self._gradients

    def _times_on(self, device: torch.device) -> torch.Tensor:
        """The stored times on ``device``, copied there once rather than on every call."""
        key = ("times", self.times.dtype, device)
        if key not in self._cache:
            self._cache[key] = self.times.to(device)
        return self._cache[key]

    def _interpolate(
        self, table: torch.Tensor, x: torch.Tensor, t: float | torch.Tensor, checked: bool = True
    ) -> torch.Tensor:
        n = self.grid.ndim
        if x.shape[-1] != n:
            raise ValueError(f"states must have shape (..., {n}), got {tuple(x.shape)}")
        if checked and not torch.isfinite(x).all():
            bad = x[~torch.isfinite(x).all(-1)][0].tolist()
            raise ValueError(f"states contain NaN or inf, e.g. {bad}")
        batch = x.shape[:-1]
        xf = x.reshape(-1, n).to(table.dtype)
        if checked and xf.dtype != x.dtype and not torch.isfinite(xf).all():  # float64 can overflow float32
            bad = x.reshape(-1, n)[~torch.isfinite(xf).all(-1)][0].tolist()
            raise ValueError(f"states overflow {table.dtype}, e.g. {bad}")
        m = xf.shape[0]
        tt = torch.as_tensor(t, dtype=torch.float64, device=x.device)
        tt = torch.broadcast_to(tt, batch).reshape(-1) if tt.ndim else tt.expand(m)
        times = self._times_on(x.device)
        if checked:
            check_time(tt, *self.time_range)
        # a stored time reads its slice alone (below): no bracket to find
        stored = self._stored.get(float(t)) if isinstance(t, (int, float)) else None
        # time bracket
        # one bracket for a scalar time (the common case); searchsorted over an expanded tensor is slow
        lookup = tt[:1].contiguous() if (isinstance(t, (int, float)) or torch.as_tensor(t).ndim == 0) else tt
        if stored is None and len(times) == 1:
            k0 = k1 = torch.zeros(m, dtype=torch.long, device=x.device)
            wt = torch.zeros(m, dtype=table.dtype, device=x.device)
        elif stored is None:
            k1 = torch.searchsorted(times, lookup.clamp(times[0], times[-1]), right=False).clamp(1, len(times) - 1)
            k1 = k1.expand(m) if lookup.shape[0] != m else k1
            k0 = k1 - 1
            wt = ((tt - times[k0]) / (times[k1] - times[k0])).clamp(0, 1).to(table.dtype)
        # space: fractional indices per dimension
        idx0, frac = [], []
        for i in range(n):
            lo, dx, size = self.grid.low[i], self.grid.spacing[i], self.grid.shape[i]
            f = (xf[:, i] - lo) / dx
            if self.grid.periodic[i]:
                f = torch.remainder(f, size)
                i0 = torch.floor(f).long().clamp(0, size - 1)
                idx0.append((i0, (i0 + 1) % size))
            else:
                if self.outside == "error" and ((f < -1e-6) | (f > size - 1 + 1e-6)).any():
                    bad = xf[(f < -1e-6) | (f > size - 1 + 1e-6)][0].tolist()
                    raise ValueError(
                        f"state {bad} lies outside the grid in dimension {i} ([{lo}, {self.grid.high[i]}]); "
                        "use outside='clamp' to use the nearest edge value"
                    )
                f = f.clamp(0, size - 1)
                i0 = torch.floor(f).long().clamp(0, size - 2)
                idx0.append((i0, i0 + 1))
            frac.append((f - i0).to(table.dtype))
        # all 2^n cell corners at once, built one dimension at a time (corner c takes the upper node
        # in dimension i where bit n-1-i of c is set): weights are products of the fractions, flat
        # indices sums of the strided node indices
        w = torch.ones(m, 1, dtype=table.dtype, device=x.device)
        lin = torch.zeros(m, 1, dtype=torch.long, device=x.device)
        for i in range(n):
            stride = int(np.prod(self.grid.shape[i + 1 :]))
            # explicit sizes, not -1: an empty batch (m = 0) must reshape too
            w = (w[:, :, None] * torch.stack([1 - frac[i], frac[i]], -1)[:, None, :]).reshape(m, 2 ** (i + 1))
            nodes = torch.stack([idx0[i][0], idx0[i][1]], -1) * stride
            lin = (lin[:, :, None] + nodes[:, None, :]).reshape(m, 2 ** (i + 1))
        flat = table.reshape(len(self.times), -1, *table.shape[1 + n :])
        extra = (1,) * (flat.ndim - 2)  # a table's own trailing dimensions (the gradient's components)
        if stored is not None:
            # a stored time: its bracket's weight is exactly 0 or 1, where lerp returns that end to
            # the bit, so one gather from that slice gives the same numbers at half the reads
            corners = flat[stored][lin]
        elif lookup.shape[0] == 1 and m * 2**n >= flat[0].numel():
            # one time for every state, and more corners than nodes: blend the two time slices once
            # and gather from the blend (the same lerp of the same numbers, so the same bits), not twice
            blend = torch.lerp(flat[k0[0]], flat[k1[0]], wt[0])
            corners = blend[lin]  # (m, 2^n, ...)
        elif lookup.shape[0] == 1:  # one time for every state: gather from one or two slices
            corners = torch.lerp(flat[k0[0]][lin], flat[k1[0]][lin], wt.reshape((m, 1, *extra)))
        else:
            corners = torch.lerp(flat[k0[:, None], lin], flat[k1[:, None], lin], wt.reshape((m, 1, *extra)))
        out = (w.reshape((m, 2**n, *extra)) * corners).sum(1)
        return out.reshape((*batch, *table.shape[1 + n :])).to(x.dtype)

    def value(self, x: torch.Tensor, t: float | torch.Tensor, checked: bool = True) -> torch.Tensor:
        """``V(x, t)`` for states ``(..., n)``; returns ``(...)``.

        ``checked=False`` skips the finite-state and time-range checks, which read a value back from
        the device: only for points the caller built inside the domain and horizon itself (a training
        step captured as a CUDA graph, which cannot read back). Times are still clamped to the stored
        range, states to the grid (``outside='error'`` still raises, so it cannot be captured)."""
        return self._interpolate(self._table("value", x.dtype, x.device), x, t, checked)

    def gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """``grad_x V(x, t)``, shape ``(..., n)``."""
        return self._interpolate(self._table("gradient", x.dtype, x.device), x, t)

    def value_and_gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(V, grad V)`` from one interpolation of a combined table."""
        both = self._interpolate(self._table("both", x.dtype, x.device), x, t)
        return both[..., 0], both[..., 1:]

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike) -> Path:
        """Write a self-describing ``.npz`` atomically (temp file in the same folder, then rename)."""
        meta = {"format": FORMAT, "system": self.system.config(), "versions": package_versions(), **self.metadata}
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                values=self.values.numpy(),
                times=self.times.numpy(),
                grid_low=np.array(self.grid.low),
                grid_high=np.array(self.grid.high),
                grid_shape=np.array(self.grid.shape),
                grid_periodic=np.array(self.grid.periodic),
                metadata=np.array(json.dumps(meta)),
            )
        return Path(path)

    @classmethod
    def load(cls, path: str | os.PathLike, outside: Literal["error", "clamp"] = "error") -> GridSolution:
        """Read a file written by :meth:`save`; corrupt or foreign files raise ``ValueError``."""
        check_input_file(path, "ground-truth file")
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["metadata"]))
                grid = Grid(
                    tuple(float(v) for v in data["grid_low"]),
                    tuple(float(v) for v in data["grid_high"]),
                    tuple(int(v) for v in data["grid_shape"]),
                    tuple(bool(v) for v in data["grid_periodic"]),
                )
                values = torch.from_numpy(data["values"].copy())
                times = torch.from_numpy(data["times"].copy())
        except (OSError, EOFError, KeyError, ValueError, TypeError, zipfile.BadZipFile) as err:
            raise ValueError(f"{path}: not a readable reach ground-truth file ({type(err).__name__}: {err})") from err
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
            raise ValueError(f"{path}: format {found!r}, expected {FORMAT!r}")
        if "system" not in meta:
            raise ValueError(f"{path}: ground-truth metadata names no system")
        system = system_from_config(meta.pop("system"))
        meta.pop("format", None)
        return cls(system=system, grid=grid, times=times, values=values, metadata=meta, outside=outside)
