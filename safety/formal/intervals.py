"""Interval arithmetic as a fourth array backend: every system's physics, bounded over boxes, soundly.

A system writes its physics once on columns (:mod:`reach.systems.arrays`). Run the same code with
:data:`INTERVAL`, whose columns are :class:`Interval` (a lower and an upper float64 tensor, batched
over boxes), and it returns intervals that contain every value the physics takes on the boxes:
the drift, the input matrices, the margins, and (through :func:`reach.integrators.make_stepper`,
which is backend-generic) a whole Euler or RK4 step with the disturbance ranging over its box.
Formal certification (:mod:`safety.formal.bounds` and what builds on it) needs exactly these, for every
registered and user-written system alike.

Sound means: every operation widens its result outward by a bound of its float64 rounding error
(a few units in the last place), so the real-valued result of the same expression lies inside.
Sums and products do it exactly: an error-free transformation (Knuth's TwoSum, Dekker's
TwoProduct) finds each one's rounding error, and the bound moves one ulp outward only on the side
the error lies, not at all where the float result is exact. So ``x + 0`` and ``x * 0`` stay
exact, and a box face that a step leaves in place stays exactly on the face, which the
certificate's closure depends on (:mod:`safety.formal.certificate`).
Intervals forget correlations (``x - x`` is not 0), so bounds of long expressions are loose on
large boxes and tighten as boxes shrink, which branch and bound provides.

A comparison of intervals is an :class:`Uncertain` truth (certainly true, possibly true); ``where``
takes the hull of both branches where the condition is uncertain.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

#: unit roundoff of float64
UNIT_ROUNDOFF = 2.0**-53
#: elementary functions (sin, cos, sqrt, atan2, tanh) err by at most this many ulps (glibc and torch: about 1)
FUNCTION_ULPS = 4.0
_TWO_PI = 2.0 * math.pi
_TINY = 1e-300  # an absolute widening that also covers underflow to zero


#: below this magnitude 1 / x overflows float64
_RECIPROCAL_OVERFLOWS_BELOW = 1.0 / 1.7976931348623157e308


def _pad(value: torch.Tensor, ulps: float = 2.0) -> torch.Tensor:
    """The rounding error bound of one operation whose result is ``value``."""
    return ulps * UNIT_ROUNDOFF * value.abs() + _TINY


#: below this magnitude a product's exact error may underflow: such results are widened by ``_pad``
_EXACT_ABOVE = 2.0**-900
#: above this magnitude Veltkamp's split may overflow: such results are widened by ``_pad``
_EXACT_BELOW = 2.0**990
_SPLIT = 2.0**27 + 1.0


def _directed(value: torch.Tensor, error: torch.Tensor, fallback: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Tight outward bounds of ``value + error`` (the exact result, ``error`` its rounding error found
    by an error-free transformation): ``value`` itself on the side the error does not reach, one ulp
    beyond it on the other. Where ``fallback`` is set the transformation may be inexact, and ``value``
    is widened by :func:`_pad` instead."""
    lo = torch.where(error < 0, torch.nextafter(value, torch.full_like(value, -math.inf)), value)
    hi = torch.where(error > 0, torch.nextafter(value, torch.full_like(value, math.inf)), value)
    lo = torch.where(fallback, value - _pad(value), lo)
    hi = torch.where(fallback, value + _pad(value), hi)
    return lo, hi


def _sum_bounds(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Outward bounds of the real ``a + b``: Knuth's TwoSum gives the exact rounding error of the float
    sum, so an exact sum (``x + 0``, or one of two equal and opposite terms) is not widened at all."""
    s = a + b
    bb = s - a
    error = (a - (s - bb)) + (b - bb)
    return _directed(s, error, ~torch.isfinite(error))


def _product_bounds(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Outward bounds of the real ``a * b``: Dekker's TwoProduct (Veltkamp's split) gives the exact
    rounding error, so an exact product (by 0, by a power of two, of short mantissas) is not
    widened. Where the split could overflow or the error underflow, :func:`_pad` widens instead."""
    a, b = torch.broadcast_tensors(a, b)
    p = a * b
    ca, cb = _SPLIT * a, _SPLIT * b
    a_hi, b_hi = ca - (ca - a), cb - (cb - b)
    a_lo, b_lo = a - a_hi, b - b_hi
    error = ((a_hi * b_hi - p) + a_hi * b_lo + a_lo * b_hi) + a_lo * b_lo
    exact_zero = (a == 0) | (b == 0)
    risky = (a.abs() > _EXACT_BELOW) | (b.abs() > _EXACT_BELOW) | (p.abs() < _EXACT_ABOVE) | ~torch.isfinite(error)
    return _directed(p, torch.where(exact_zero, torch.zeros_like(error), error), risky & ~exact_zero)


def sin_interval(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds of ``sin`` over ``[lo, hi]`` elementwise: the endpoints' values, and 1 (or -1) wherever a
    maximum ``pi/2 + 2 k pi`` (a minimum ``-pi/2 + 2 k pi``) lies inside; widened for rounding."""
    s_lo, s_hi = torch.sin(lo), torch.sin(hi)
    low, high = torch.minimum(s_lo, s_hi), torch.maximum(s_lo, s_hi)
    # a peak p + 2 k pi lies in [lo, hi] iff ceil((lo - p) / 2pi) <= floor((hi - p) / 2pi); the division's
    # rounding is covered by also counting a peak within a few ulps of an end (then the bound is 1: sound)
    slack = 8 * UNIT_ROUNDOFF * (1.0 + torch.maximum(lo.abs(), hi.abs()))
    for peak, extreme in ((0.5 * math.pi, 1.0), (-0.5 * math.pi, -1.0)):
        inside = torch.ceil((lo - slack - peak) / _TWO_PI) <= torch.floor((hi + slack - peak) / _TWO_PI)
        if extreme > 0:
            high = torch.where(inside, torch.ones_like(high), high)
        else:
            low = torch.where(inside, -torch.ones_like(low), low)
    error = FUNCTION_ULPS * UNIT_ROUNDOFF * (1.0 + torch.maximum(lo.abs(), hi.abs()))
    return (low - error).clamp(min=-1.0), (high + error).clamp(max=1.0)


def cos_interval(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds of ``cos`` over ``[lo, hi]``: ``cos x = sin(x + pi/2)`` (the shift's rounding widened)."""
    shift = 0.5 * math.pi
    pad = 2 * UNIT_ROUNDOFF * (shift + torch.maximum(lo.abs(), hi.abs()))
    return sin_interval(lo + shift - pad, hi + shift + pad)


class Uncertain:
    """The truth of a comparison over boxes: ``certain`` where it holds for every value, ``possible``
    where it holds for some (``certain`` implies ``possible``)."""

    __slots__ = ("certain", "possible")

    def __init__(self, certain: torch.Tensor, possible: torch.Tensor) -> None:
        self.certain, self.possible = certain, possible

    def __bool__(self) -> bool:
        raise TypeError("an interval comparison has no single truth value; use INTERVAL.where on it")


class Interval:
    """``[lo, hi]`` elementwise: float64 tensors of one shape (one entry per box), or broadcastable.

    Arithmetic with another interval or a Python number gives an interval containing every result
    of the real operation on members of the operands."""

    __slots__ = ("hi", "lo")
    __array_priority__ = 1000  # numpy scalars defer to us

    def __init__(self, lo: Any, hi: Any = None) -> None:
        lo = torch.as_tensor(lo, dtype=torch.float64)
        hi = lo if hi is None else torch.as_tensor(hi, dtype=torch.float64)
        self.lo, self.hi = lo, hi

    @classmethod
    def point(cls, value: Any) -> Interval:
        return cls(value, value)

    def __repr__(self) -> str:
        return f"Interval(lo={self.lo}, hi={self.hi})"

    @property
    def width(self) -> torch.Tensor:
        return self.hi - self.lo

    def contains(self, value: torch.Tensor) -> torch.Tensor:
        return (self.lo <= value) & (value <= self.hi)

    # ---------------------------------------------------------------- arithmetic
    @staticmethod
    def of(value: Any) -> Interval:
        """``value`` as an interval: itself if it is one, else the point interval of a number or tensor."""
        return value if isinstance(value, Interval) else Interval.point(value)

    def __add__(self, other: Any) -> Interval:
        other = self.of(other)
        return Interval(_sum_bounds(self.lo, other.lo)[0], _sum_bounds(self.hi, other.hi)[1])

    __radd__ = __add__

    def __neg__(self) -> Interval:
        return Interval(-self.hi, -self.lo)

    def __pos__(self) -> Interval:
        return self

    def __sub__(self, other: Any) -> Interval:
        return self + (-self.of(other))

    def __rsub__(self, other: Any) -> Interval:
        return self.of(other) + (-self)

    def __mul__(self, other: Any) -> Interval:
        other = self.of(other)
        pairs = ((self.lo, other.lo), (self.lo, other.hi), (self.hi, other.lo), (self.hi, other.hi))
        bounds = [_product_bounds(a, b) for a, b in pairs]
        lo = torch.stack(torch.broadcast_tensors(*[low for low, _ in bounds])).amin(0)
        hi = torch.stack(torch.broadcast_tensors(*[high for _, high in bounds])).amax(0)
        return Interval(lo, hi)

    __rmul__ = __mul__

    def reciprocal(self) -> Interval:
        """``1 / x``; refuses an interval that contains 0 (the real result is unbounded) or comes so
        near it that the reciprocal overflows float64 (an infinite bound would turn ``0 * inf`` into NaN)."""
        if bool(((self.lo <= 0) & (self.hi >= 0)).any()):
            raise ZeroDivisionError("interval division by an interval that contains 0")
        if bool(((self.lo.abs() < _RECIPROCAL_OVERFLOWS_BELOW) | (self.hi.abs() < _RECIPROCAL_OVERFLOWS_BELOW)).any()):
            raise ZeroDivisionError("interval division by an interval so near 0 that its reciprocal overflows")
        lo, hi = 1.0 / self.hi, 1.0 / self.lo
        return Interval(lo - _pad(lo), hi + _pad(hi))

    def __truediv__(self, other: Any) -> Interval:
        return self * self.of(other).reciprocal()

    def __rtruediv__(self, other: Any) -> Interval:
        return self.of(other) * self.reciprocal()

    def __pow__(self, exponent: int) -> Interval:
        if not isinstance(exponent, int) or exponent < 0:
            raise TypeError(f"interval powers take non-negative integer exponents, got {exponent!r}")
        if exponent == 0:
            return Interval.point(torch.ones_like(self.lo))
        a, b = self.lo**exponent, self.hi**exponent
        lo, hi = torch.minimum(a, b), torch.maximum(a, b)
        if exponent % 2 == 0:  # even: 0 where the interval straddles it
            lo = torch.where((self.lo <= 0) & (self.hi >= 0), torch.zeros_like(lo), lo)
        return Interval(lo - _pad(lo, 2.0 * exponent), hi + _pad(hi, 2.0 * exponent))

    # ---------------------------------------------------------------- comparisons
    def __gt__(self, other: Any) -> Uncertain:
        other = self.of(other)
        return Uncertain(self.lo > other.hi, self.hi > other.lo)

    def __ge__(self, other: Any) -> Uncertain:
        other = self.of(other)
        return Uncertain(self.lo >= other.hi, self.hi >= other.lo)

    def __lt__(self, other: Any) -> Uncertain:
        return self.of(other) > self

    def __le__(self, other: Any) -> Uncertain:
        return self.of(other) >= self


def _hull(a: Interval, b: Interval) -> Interval:
    return Interval(torch.minimum(a.lo, b.lo), torch.maximum(a.hi, b.hi))


class IntervalBackend:
    """The column backend of :mod:`reach.systems.arrays` on :class:`Interval` columns."""

    name = "interval"

    @staticmethod
    def cos(a: Any) -> Interval:
        a = Interval.of(a)
        return Interval(*cos_interval(a.lo, a.hi))

    @staticmethod
    def sin(a: Any) -> Interval:
        a = Interval.of(a)
        return Interval(*sin_interval(a.lo, a.hi))

    @staticmethod
    def sqrt(a: Any) -> Interval:
        """Monotone; a lower end below 0 (an enclosure of a non-negative quantity) is taken as 0."""
        a = Interval.of(a)
        lo, hi = torch.sqrt(a.lo.clamp(min=0.0)), torch.sqrt(a.hi.clamp(min=0.0))
        return Interval((lo - _pad(lo, FUNCTION_ULPS)).clamp(min=0.0), hi + _pad(hi, FUNCTION_ULPS))

    @staticmethod
    def abs(a: Any) -> Interval:
        a = Interval.of(a)
        straddles = (a.lo <= 0) & (a.hi >= 0)
        lo = torch.where(straddles, torch.zeros_like(a.lo), torch.minimum(a.lo.abs(), a.hi.abs()))
        return Interval(lo, torch.maximum(a.lo.abs(), a.hi.abs()))

    @staticmethod
    def sign(a: Any) -> Interval:
        a = Interval.of(a)
        return Interval(torch.sign(a.lo), torch.sign(a.hi))

    @staticmethod
    def minimum(a: Any, b: Any) -> Interval:
        a, b = Interval.of(a), Interval.of(b)
        return Interval(torch.minimum(a.lo, b.lo), torch.minimum(a.hi, b.hi))

    @staticmethod
    def maximum(a: Any, b: Any) -> Interval:
        a, b = Interval.of(a), Interval.of(b)
        return Interval(torch.maximum(a.lo, b.lo), torch.maximum(a.hi, b.hi))

    @staticmethod
    def clip(a: Any, lo: float, hi: float) -> Interval:
        a = Interval.of(a)
        return Interval(a.lo.clamp(lo, hi), a.hi.clamp(lo, hi))

    @staticmethod
    def where(condition: Uncertain | torch.Tensor | bool, a: Any, b: Any) -> Interval:
        """``a`` where the condition certainly holds, ``b`` where it certainly fails, else their hull."""
        a, b = Interval.of(a), Interval.of(b)
        if not isinstance(condition, Uncertain):
            certain = torch.as_tensor(condition)
            condition = Uncertain(certain, certain)
        hull = _hull(a, b)
        lo = torch.where(condition.certain, a.lo, torch.where(condition.possible, hull.lo, b.lo))
        hi = torch.where(condition.certain, a.hi, torch.where(condition.possible, hull.hi, b.hi))
        return Interval(lo, hi)

    @staticmethod
    def norm(columns: Sequence[Any]) -> Interval:
        """The Euclidean norm: monotone in each column's magnitude."""
        squares = [IntervalBackend.abs(c) ** 2 for c in columns]
        total = squares[0]
        for s in squares[1:]:
            total = total + s
        return IntervalBackend.sqrt(total)

    @staticmethod
    def hypot(dx: Any, dy: Any) -> Interval:
        return IntervalBackend.norm([dx, dy])

    @staticmethod
    def atan2(y: Any, x: Any) -> Interval:
        """The angle of a box of points: over a box that keeps off the origin and off the negative
        x-axis (the branch cut) its extremes are at corners; otherwise the whole ``[-pi, pi]``."""
        y, x = Interval.of(y), Interval.of(x)
        corners = torch.stack(
            torch.broadcast_tensors(
                torch.atan2(y.lo, x.lo), torch.atan2(y.lo, x.hi), torch.atan2(y.hi, x.lo), torch.atan2(y.hi, x.hi)
            )
        )
        cut = (x.lo <= 0) & (y.lo <= 0) & (y.hi >= 0)  # touches the origin or the negative x-axis
        error = FUNCTION_ULPS * UNIT_ROUNDOFF * math.pi
        lo = torch.where(cut, torch.full_like(corners[0], -math.pi), corners.amin(0) - error)
        hi = torch.where(cut, torch.full_like(corners[0], math.pi), corners.amax(0) + error)
        return Interval(lo, hi)

    @staticmethod
    def wrap_angle(a: Any) -> Interval:
        """Into ``[-pi, pi)``: shifted by whole turns where the interval fits inside one branch,
        else the whole ``[-pi, pi]``."""
        a = Interval.of(a)
        turns = torch.round((0.5 * (a.lo + a.hi)) / _TWO_PI)
        lo, hi = a.lo - turns * _TWO_PI, a.hi - turns * _TWO_PI
        error = _pad(torch.maximum(lo.abs(), hi.abs()), 4.0)
        lo, hi = lo - error, hi + error
        fits = (lo >= -math.pi) & (hi < math.pi)
        return Interval(torch.where(fits, lo, -math.pi), torch.where(fits, hi, math.pi))

    @staticmethod
    def unbind(x: Interval) -> list[Interval]:
        return [Interval(lo, hi) for lo, hi in zip(x.lo.unbind(-1), x.hi.unbind(-1))]

    @staticmethod
    def stack(columns: Sequence[Any], like: Any = None) -> Interval:
        parts = [Interval.of(c) for c in columns]
        los = torch.broadcast_tensors(*[p.lo for p in parts])
        his = torch.broadcast_tensors(*[p.hi for p in parts])
        return Interval(torch.stack(los, -1), torch.stack(his, -1))

    @staticmethod
    def axpy(x: Any, h: float, k: Any) -> Interval:
        return Interval.of(x) + h * Interval.of(k)


INTERVAL = IntervalBackend()


def box_columns(lo: torch.Tensor, hi: torch.Tensor) -> list[Interval]:
    """The columns of boxes ``[lo, hi]`` (``(B, n)`` each): one interval per dimension."""
    lo, hi = torch.as_tensor(lo, dtype=torch.float64), torch.as_tensor(hi, dtype=torch.float64)
    return [Interval(a, b) for a, b in zip(lo.unbind(-1), hi.unbind(-1))]
