"""Array backends that let one physics definition run on Python floats, NumPy and torch.

A system writes its physics once, on *columns*: one array (or one Python float) per state
dimension. The same code then runs on

* ``FLOAT``: Python floats with :mod:`math`; the fastest path for a single environment step, where
  per-call overhead of array libraries would dominate (a NumPy call costs ~1 us, a torch call ~5 us);
* ``NUMPY``: NumPy arrays of any shape; used by the batched vector environments;
* ``TORCH``: torch tensors of any shape, dtype and device; used by the grid solver, training and
  safety code (autograd flows through it).

Only a handful of operations are needed, so each backend is a small object with the same method
names. Columns may mix arrays and Python numbers (for example a constant entry of an input matrix);
arithmetic broadcasts, and :meth:`stack` materialises constants where a full array is needed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

PI = math.pi
TAU = 2.0 * math.pi

Column = Any  # float | np.ndarray | torch.Tensor

#: Sparse input matrix: {(state index, input index): entry}; absent entries are zero.
InputMatrix = Mapping[tuple[int, int], Column]


def is_number(value: Column, number: float) -> bool:
    """Whether ``value`` is the plain Python number ``number`` (an array never is)."""
    return isinstance(value, (int, float)) and value == number


class FloatBackend:
    """Columns are Python floats; state vectors are lists of floats."""

    name = "float"
    cos = staticmethod(math.cos)
    sin = staticmethod(math.sin)
    sqrt = staticmethod(math.sqrt)
    atan2 = staticmethod(math.atan2)

    @staticmethod
    def unbind(x: Sequence[float]) -> Sequence[float]:
        return x

    @staticmethod
    def stack(columns: Sequence[Column], like: Column = None) -> list[float]:
        return [float(c) for c in columns]

    @staticmethod
    def abs(a: float) -> float:
        return abs(a)

    @staticmethod
    def sign(a: float) -> float:
        # Same convention as torch.sign / numpy.sign: sign(0) == 0.
        return 1.0 if a > 0.0 else (-1.0 if a < 0.0 else 0.0)

    @staticmethod
    def minimum(a: float, b: float) -> float:
        return a if a <= b else b

    @staticmethod
    def where(condition: bool, a: float, b: float) -> float:
        return a if condition else b

    @staticmethod
    def clip(a: float, lo: float, hi: float) -> float:
        return lo if a < lo else (hi if a > hi else a)

    @staticmethod
    def hypot(dx: float, dy: float) -> float:
        return math.hypot(dx, dy)

    @staticmethod
    def norm(columns: Sequence[float]) -> float:
        """The Euclidean norm across columns (a ball of inputs' support function)."""
        return math.sqrt(sum(c * c for c in columns))

    @staticmethod
    def wrap_angle(a: float) -> float:
        # math.remainder is exact (IEEE remainder), so the result lies in [-pi, pi] without
        # rounding; the single value +pi is moved to -pi to make the interval half-open.
        r = math.remainder(a, TAU)
        return r - TAU if r >= PI else r

    @staticmethod
    def axpy(x: Sequence[float], h: float, k: Sequence[float]) -> list[float]:
        """x + h * k, element by element."""
        return [a + h * b for a, b in zip(x, k)]


class NumpyBackend:
    """Columns are NumPy arrays of one common shape (or Python floats that broadcast)."""

    name = "numpy"
    cos = staticmethod(np.cos)
    sin = staticmethod(np.sin)
    sqrt = staticmethod(np.sqrt)
    atan2 = staticmethod(np.arctan2)
    abs = staticmethod(np.abs)
    sign = staticmethod(np.sign)
    minimum = staticmethod(np.minimum)
    where = staticmethod(np.where)
    clip = staticmethod(np.clip)
    hypot = staticmethod(np.hypot)

    @staticmethod
    def norm(columns: Sequence[Column]) -> np.ndarray:
        """The Euclidean norm across columns."""
        return np.sqrt(sum(np.square(c) for c in columns))

    @staticmethod
    def unbind(x: np.ndarray) -> list[np.ndarray]:
        return [x[..., i] for i in range(x.shape[-1])]

    @staticmethod
    def stack(columns: Sequence[Column], like: Column = None) -> np.ndarray:
        ref = like if like is not None else next(c for c in columns if isinstance(c, np.ndarray))
        shape = np.shape(ref)
        dtype = np.result_type(*[c for c in columns if isinstance(c, np.ndarray)] or [ref])
        return np.stack([np.broadcast_to(np.asarray(c, dtype=dtype), shape) for c in columns], axis=-1)

    @staticmethod
    def wrap_angle(a: np.ndarray) -> np.ndarray:
        w = a - TAU * np.round(a / TAU)
        w = np.where(w >= PI, w - TAU, w)
        return np.where(w < -PI, w + TAU, w)

    @staticmethod
    def axpy(x: np.ndarray, h: float, k: np.ndarray) -> np.ndarray:
        return x + h * k


class TorchBackend:
    """Columns are torch tensors of one common shape (or Python floats that broadcast).

    Every operation is differentiable where the math is; :meth:`hypot` returns a zero (sub)gradient
    at the origin instead of NaN, so failure margins stay differentiable when two cars coincide.
    """

    name = "torch"
    cos = staticmethod(torch.cos)
    sin = staticmethod(torch.sin)
    sqrt = staticmethod(torch.sqrt)
    atan2 = staticmethod(torch.atan2)
    abs = staticmethod(torch.abs)
    sign = staticmethod(torch.sign)
    where = staticmethod(torch.where)

    @staticmethod
    def unbind(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return x.unbind(-1)

    @staticmethod
    def stack(columns: Sequence[Column], like: Column = None) -> torch.Tensor:
        ref = like if like is not None else next(c for c in columns if isinstance(c, torch.Tensor))
        cols = [c if isinstance(c, torch.Tensor) else torch.full_like(ref, float(c)) for c in columns]
        return torch.stack(torch.broadcast_tensors(*cols), dim=-1)

    @staticmethod
    def minimum(a: Column, b: Column) -> torch.Tensor:
        if not isinstance(a, torch.Tensor):
            a, b = b, a
        return torch.minimum(a, torch.as_tensor(b, dtype=a.dtype, device=a.device))

    @staticmethod
    def clip(a: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
        return torch.clamp(a, lo, hi)

    @staticmethod
    def norm(columns: Sequence[Column]) -> torch.Tensor:
        """The Euclidean norm across columns, with a zero (sub)gradient where it is 0."""
        ref = next(c for c in columns if isinstance(c, torch.Tensor))
        cols = [c if isinstance(c, torch.Tensor) else torch.full_like(ref, float(c)) for c in columns]
        return torch.linalg.vector_norm(torch.stack(torch.broadcast_tensors(*cols)), dim=0)

    @staticmethod
    def hypot(dx: torch.Tensor, dy: torch.Tensor) -> torch.Tensor:
        r = torch.hypot(dx, dy)
        nonzero = r > 0
        if not (torch.is_grad_enabled() and (dx.requires_grad or dy.requires_grad)):
            # no graph to protect: the same values (0 where r is 0 or NaN) at a third of the cost
            return torch.where(nonzero, r, 0.0)
        # Evaluate hypot on safe inputs where r == 0 so that backward never divides 0 by 0.
        safe = torch.hypot(torch.where(nonzero, dx, torch.ones_like(dx)), torch.where(nonzero, dy, torch.ones_like(dy)))
        return torch.where(nonzero, safe, torch.zeros_like(r))

    @staticmethod
    def wrap_angle(a: torch.Tensor) -> torch.Tensor:
        w = a - TAU * torch.round(a / TAU)
        w = torch.where(w >= PI, w - TAU, w)
        return torch.where(w < -PI, w + TAU, w)

    @staticmethod
    def axpy(x: torch.Tensor, h: float, k: torch.Tensor) -> torch.Tensor:
        return x + h * k


FLOAT = FloatBackend()
NUMPY = NumpyBackend()
TORCH = TorchBackend()

Backend = FloatBackend | NumpyBackend | TorchBackend
