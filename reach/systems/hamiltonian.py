"""The Hamiltonian of a control-affine system at fixed states, as a function of the costate.

For box-bounded inputs the optimal inputs are box corners, and ``H(x, p) = opt_u opt_d p . xdot``
has a closed form (``docs/concepts.md``)::

    H = p . f(x) + sum_j (c_j s_j + sigma hw_j |s_j|),    s = G(x)^T p

over the control's and the disturbance's input dimensions ``j`` (centre ``c``, half width ``hw``,
``sigma = +1`` for the maximising player, ``-1`` for the minimising one). A side whose inputs lie
in a ball of radius ``r`` adds ``c . s + sigma r |s|_2`` instead.

:class:`FixedStateHamiltonian` evaluates ``f(x)`` and ``G(x)`` once and keeps the costate as the
only argument. That is the grid solver's situation: the states are the grid, fixed for the whole
solve, while ``H`` is read at every node in every stage of every time step. Built once, it also

- merges the terms per costate component: a switching function with one number entry
  (``s_j = g p_i``, as for most inputs) becomes a linear and an ``|p_i|`` coefficient, so an input
  costs one pass over the grid instead of three;
- can drop drift and matrix entries that are zero at every state (``prune``): systems write
  ``0.0 * x[k]`` to give a zero column its shape, which would cost the grid two passes each;
- folds a number factor per costate component into the coefficients (``scale``), so a caller
  holding ``p_i / scale_i`` needs no pass to undo it.

:meth:`ControlAffineSystem.hamiltonian_columns` is this class built and called once, so there is
one implementation of ``H``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from reach.systems.arrays import Backend, Column, is_number

#: one side's inputs: (matrix ``{(state i, input j): G_ij}``, centres, half widths, sigma, and the
#: radius of a ball of inputs or ``None`` for a box)
Side = tuple[dict[tuple[int, int], Column], Sequence[float], Sequence[float], float, float | None]


def _is_zero(value: Column, prune: bool) -> bool:
    """Whether ``value`` is the number 0, or (with ``prune``) an array of zeros only."""
    if isinstance(value, (int, float)):
        return value == 0
    if not prune:
        return False
    if isinstance(value, torch.Tensor):
        return not bool(value.any())  # one read of a small column, once per solve
    return not value.any()


def _fits(t: torch.Tensor, shape: torch.Size) -> bool:
    """Whether ``t`` broadcasts to ``shape`` without enlarging it (checked by hand:
    ``torch.broadcast_shapes`` imports sympy on first use, 0.3 s of a small solve)."""
    return t.dim() <= len(shape) and all(a in (1, b) for a, b in zip(reversed(t.shape), reversed(shape)))


def _axpy(h: Column | None, k: Column, p: Column) -> Column:
    """``h + k p``: in place on ``h`` where that is safe (no autograd, ``h`` keeps its shape), else a new
    array. ``h`` is always an array this module made, never a caller's."""
    if h is None:
        return k * p
    in_place = isinstance(h, torch.Tensor) and isinstance(p, torch.Tensor) and not torch.is_grad_enabled()
    if in_place and _fits(p, h.shape) and (not isinstance(k, torch.Tensor) or _fits(k, h.shape)):
        return h.addcmul_(k, p) if isinstance(k, torch.Tensor) else h.add_(p, alpha=k)
    return h + k * p


class FixedStateHamiltonian:
    """``p -> H(x, scale * p)`` at fixed states ``x`` (see the module docstring)."""

    def __init__(
        self,
        drift: Sequence[Column],
        sides: Sequence[Side],
        xp: Backend,
        *,
        scale: Sequence[float] | None = None,
        prune: bool = False,
    ) -> None:
        n = len(drift)
        scale = [1.0] * n if scale is None else [float(s) for s in scale]
        if len(scale) != n:
            raise ValueError(f"scale has {len(scale)} factors for {n} costate components")
        bad = [f for f in scale if not (math.isfinite(f) and f != 0.0)]
        if bad:  # a NaN would spread into every H, a zero would silently drop a component
            raise ValueError(f"scale factors must be finite and non-zero, got {bad[0]} in {scale}")
        self._xp = xp
        #: coefficient of p_i, of |p_i|, and the switching functions that mix components or vary with x
        self.linear: list[Column | None] = [None] * n
        self.absolute: list[float] = [0.0] * n
        self.switches: list[tuple[float, float, list[tuple[int, Column]]]] = []
        #: ball sides: (centres, sigma r, per input the terms of its switching function)
        self.balls: list[tuple[Sequence[float], float, list[list[tuple[int, Column]]]]] = []
        for i, f in enumerate(drift):
            if not _is_zero(f, prune):
                self.linear[i] = f if scale[i] == 1.0 else f * scale[i]
        for matrix, centres, half_widths, sigma, radius in sides:
            entries: list[list[tuple[int, Column]]] = [[] for _ in centres]
            for (i, j), g in matrix.items():
                if not _is_zero(g, prune):
                    entries[j].append((i, g if scale[i] == 1.0 else g * scale[i]))
            if radius is not None:  # a ball: the norm of the whole switching vector, not one input at a time
                self.balls.append((tuple(centres), sigma * radius, entries))
                continue
            for c, hw, terms in zip(centres, half_widths, entries):
                if not terms or (c == 0.0 and hw == 0.0):
                    continue  # s_j = 0, or an input fixed at zero: nothing to add
                if len(terms) == 1 and isinstance(terms[0][1], (int, float)):
                    ((i, g),) = terms  # s_j = g p_i: c g p_i + sigma hw |g| |p_i|
                    if c != 0.0:
                        self.linear[i] = c * g if self.linear[i] is None else self.linear[i] + c * g
                    self.absolute[i] += sigma * hw * abs(g)
                else:
                    self.switches.append((c, sigma * hw, terms))

    def __call__(self, p: Sequence[Column]) -> Column:
        """``H`` at the fixed states for costate columns ``p`` (each ``p_i`` already divided by ``scale_i``)."""
        h: Column | None = None
        abs_ = self._xp.abs
        for k, pi in zip(self.linear, p):
            if k is not None:
                h = _axpy(h, k, pi)
        for k, pi in zip(self.absolute, p):
            if k != 0.0:
                h = _axpy(h, k, abs_(pi))
        for c, weight, terms in self.switches:
            (i, g), rest = terms[0], terms[1:]
            # s_j = sum g p_i; a lone unit entry is p_i itself, read but never written
            s = p[i] if not rest and is_number(g, 1.0) else g * p[i]
            for i, g in rest:
                s = _axpy(s, g, p[i])
            if c != 0.0:
                h = _axpy(h, c, s)
            if weight != 0.0:
                h = _axpy(h, weight, abs_(s))
        for centres, weight, entries in self.balls:
            switches = []
            for c, terms in zip(centres, entries):
                if not terms:
                    continue
                s = self._switch(terms, p)
                if c != 0.0:
                    h = _axpy(h, c, s)
                switches.append(s)
            if switches:  # |s|_2 with a zero subgradient at s = 0 (autograd flows through H in training)
                h = _axpy(h, weight, self._xp.norm(switches))
        return 0.0 if h is None else h

    @staticmethod
    def _switch(terms: list[tuple[int, Column]], p: Sequence[Column]) -> Column:
        """``s_j = sum g p_i`` over an input's terms (a new array: the caller may write to it)."""
        (i, g), rest = terms[0], terms[1:]
        s = g * p[i]
        for i, g in rest:
            s = s + g * p[i]
        return s
