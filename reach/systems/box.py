"""Input boxes, one ``[low, high]`` per input, in their own module so bounds need not import the base class.

Systems declare their control and disturbance bounds as boxes; solvers, policies and the optimal
inputs read their centres and half-widths.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Box:
    """A box ``[low, high]`` of inputs, one interval per input dimension."""

    low: tuple[float, ...]
    high: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.low) != len(self.high):
            raise ValueError(f"Box bounds differ in length: low={self.low}, high={self.high}")
        for lo, hi in zip(self.low, self.high):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"Box bound must be finite with low <= high, got [{lo}, {hi}]")

    @classmethod
    def symmetric(cls, bounds: Sequence[float]) -> Box:
        """The box ``[-b, b]`` per dimension."""
        return cls(tuple(-float(b) for b in bounds), tuple(float(b) for b in bounds))

    @property
    def dim(self) -> int:
        return len(self.low)

    @property
    def center(self) -> tuple[float, ...]:
        return tuple(0.5 * (lo + hi) for lo, hi in zip(self.low, self.high))

    @property
    def half_width(self) -> tuple[float, ...]:
        return tuple(0.5 * (hi - lo) for lo, hi in zip(self.low, self.high))


#: the box of no inputs (a system without a disturbance)
NO_INPUT = Box((), ())
