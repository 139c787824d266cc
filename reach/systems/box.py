"""Input sets: boxes, one ``[low, high]`` per input, and Euclidean balls, in their own module so
bounds need not import the base class.

Systems declare their control and disturbance bounds as a :class:`Box` (most systems) or a
:class:`Ball` (a thrust of bounded magnitude in any direction: DeepReach's rockets). The Hamiltonian
and the optimal inputs are derived for both (``docs/concepts.md``): over a box, ``max_u s . u`` is
``s . c + sum_j hw_j |s_j|`` at a corner; over a ball, ``s . c + r |s|_2`` at ``c + r s / |s|_2``.
A ball's ``low``, ``high`` and ``half_width`` are its bounding box, which is what bounds (the grid
solver's dissipation) and normalised actions (envs) need; code that enumerates corners or samples
the box refuses a ball by name (:func:`require_box`). :func:`project_inputs` moves inputs into
either kind of set (filters clip a nominal input with it, rollouts measure how far a disturbance
lies outside).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch


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


@dataclass(frozen=True)
class Ball:
    """A Euclidean ball ``{u : |u - center|_2 <= radius}`` of inputs."""

    center: tuple[float, ...]
    radius: float

    def __post_init__(self) -> None:
        if not self.center:
            raise ValueError("Ball: center needs at least one dimension")
        if not all(math.isfinite(c) for c in self.center):
            raise ValueError(f"Ball: center must be finite, got {self.center}")
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"Ball: radius must be finite and positive, got {self.radius}")

    @classmethod
    def centred(cls, dim: int, radius: float) -> Ball:
        """The ball of ``radius`` around the origin in ``dim`` dimensions."""
        return cls((0.0,) * int(dim), float(radius))

    @property
    def dim(self) -> int:
        return len(self.center)

    @property
    def half_width(self) -> tuple[float, ...]:
        """Half widths of the bounding box (every one the radius)."""
        return (float(self.radius),) * self.dim

    @property
    def low(self) -> tuple[float, ...]:
        return tuple(c - self.radius for c in self.center)

    @property
    def high(self) -> tuple[float, ...]:
        return tuple(c + self.radius for c in self.center)


#: what a system may declare as its control or disturbance bounds
InputSet = Box | Ball


def project_inputs(u: torch.Tensor, bounds: InputSet) -> torch.Tensor:
    """``u`` moved into the input set: clipped to a box, scaled back onto a ball along ``u - c``."""
    if isinstance(bounds, Ball):
        c = u.new_tensor(bounds.center)
        norm = torch.linalg.vector_norm(u - c, dim=-1, keepdim=True)
        return c + (u - c) * torch.clamp(bounds.radius / norm.clamp_min(1e-300), max=1.0)
    return torch.minimum(torch.maximum(u, u.new_tensor(bounds.low)), u.new_tensor(bounds.high))


def require_box(bounds: InputSet, what: str) -> Box:
    """``bounds`` if it is a :class:`Box`; a :class:`Ball` raises ``ValueError`` naming ``what``, for the
    code that enumerates a box's corners or samples it uniformly (a ball's corners lie outside it)."""
    if isinstance(bounds, Ball):
        raise ValueError(
            f"{what} needs box inputs (it enumerates corners or samples the box); this system's inputs lie in "
            f"a ball of radius {bounds.radius:g}"
        )
    return bounds


#: the box of no inputs (a system without a disturbance)
NO_INPUT = Box((), ())
