"""Upwind HJ-WENO5 derivatives (Jiang & Peng 2000) along one grid dimension, batched over the grid.

For node ``i`` the left-biased derivative uses the five one-sided differences
``D_{i-3} .. D_{i+1}`` (``D_k = (V_{k+1} - V_k) / dx``) and the right-biased one ``D_{i+2} .. D_{i-2}``.
Both read the same three smoothness indicators of each triple of consecutive differences, so they are
computed once for the whole padded line and sliced: this halves the work of a naive implementation.

Boundaries: periodic dimensions wrap; other dimensions are padded with three ghost nodes that
*extrapolate away from zero* (``V_edge + sign(V_edge) |V_edge - V_inner| k``), so that the zero level
set never enters from the box edge.
"""

from __future__ import annotations

import functools

import torch

EPS = 1e-6  # Jiang & Peng's epsilon in the nonlinear weights


def pad(v: torch.Tensor, dim: int, periodic: bool, width: int = 3) -> torch.Tensor:
    """``v`` with ``width`` ghost nodes on both sides of dimension ``dim``."""
    n = v.shape[dim]
    if periodic:
        return torch.cat([v.narrow(dim, n - width, width), v, v.narrow(dim, 0, width)], dim)
    # both ends at once, in a handful of operations on the thin ghost slabs (a per-end version took
    # twice as many, each a dispatch on every stage of a solve): the edge and its neighbour repeated
    # width times per end, and the ghosts' distances width .. 1 | 1 .. width from the edge
    ghost_indices = _ghost_indices_uncached if torch.compiler.is_compiling() else _ghost_indices
    edge_index, inner_index, distance = ghost_indices(n, width, v.ndim, dim, v.dtype, v.device)
    edge = v.index_select(dim, edge_index)
    step = (edge - v.index_select(dim, inner_index)).abs_().mul_(edge.sign())
    ghosts = step.mul_(distance).add_(edge)
    return torch.cat([ghosts.narrow(dim, 0, width), v, ghosts.narrow(dim, width, width)], dim)


def _ghost_indices_uncached(
    n: int, width: int, ndim: int, dim: int, dtype: torch.dtype, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The edge and inner node of each ghost of :func:`pad` (left ghosts first) and their distances,
    shaped to broadcast along ``dim`` of an ``ndim``-dimensional grid. Cached in eager mode
    (:func:`_ghost_indices`); torch.compile traces this one, as constants of its graph."""
    edge = torch.tensor([0] * width + [n - 1] * width, device=device)
    inner = torch.tensor([1] * width + [n - 2] * width, device=device)
    shape = [1] * ndim
    shape[dim] = 2 * width
    distance = [float(width - k) for k in range(width)] + [float(k + 1) for k in range(width)]
    return edge, inner, torch.tensor(distance, dtype=dtype, device=device).reshape(shape)


_ghost_indices = functools.cache(_ghost_indices_uncached)


#: :func:`mean_and_half_jump` returns ``SCALE * dx`` times the mean and the half jump of the two
#: one-sided derivatives; the caller folds the factor into its own (one pass less over the grid each)
SCALE = -12.0


def _weight(curvature: torch.Tensor, slope: torch.Tensor) -> torch.Tensor:
    """``1 / (curvature + 3/13 slope^2)^2``: a WENO5 nonlinear weight before its linear factor, up to a
    factor common to all three weights (see :func:`mean_and_half_jump`)."""
    return torch.addcmul(curvature, slope, slope, value=3.0 / 13.0).pow_(-2)


def mean_and_half_jump(v: torch.Tensor, dim: int, dx: float, periodic: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """``(left + right) / 2`` and ``(right - left) / 2`` of the WENO5 derivatives along ``dim``, times
    ``SCALE * dx``: what a Lax-Friedrichs Hamiltonian reads (the mean as the costate, the half jump
    times the dissipation).

    Written in Jiang & Peng's own form (their eq. 2.11-2.12, 2000), in which both biases share a
    fourth-order central part and differ by a correction ``Phi`` of the second differences
    ``a, b, c, d``::

        left  = central - Phi(a, b, c, d)        right = central + Phi(a', b', c', d')
        Phi   = 1/3 w0 (a - 2b + c) + 1/6 (w2 - 1/2) (b - 2c + d)

    so the mean is the central part plus half the difference of the corrections, and the half jump
    half their sum: neither one-sided derivative is ever formed. An eager solve is bound by passes
    over memory, so this is written for few of them:

    - no difference is divided by ``dx``. Jiang & Peng's weights ``1 / (IS + eps)^2`` then see
      ``IS dx^2``, and ``eps dx^2`` in place of ``eps`` gives each weight times ``dx^4``;
    - each indicator ``IS = 13 (curvature^2 + 3/13 slope^2)``, with the 13 and ``eps`` folded into
      the curvature, so a common factor multiplies every weight;
    - each indicator and weight is computed once on the padded line and read by both biases (the
      left bias's ``IS0, IS1, IS2`` are the right bias's ``IS2, IS1, IS0`` two nodes on), and the
      fourth differences ``a - 2b + c`` likewise;
    - the normalisation of each bias is one fused divide-and-add per output.

    Factors common to the three weights of a node cancel in their normalised combination, so the
    result is Jiang & Peng's to round-off (``tests/test_groundtruth.py`` checks the derived
    :func:`derivatives` against the textbook formula in float64). ``eps`` sits on the smoothness
    ``IS / 12`` (the textbook's ``s``, as the MATLAB toolbox and hj_reachability use it).
    """
    n = v.shape[dim]
    d = torch.diff(pad(v, dim, periodic), dim=dim)  # n + 5 first differences, times dx
    dd = torch.diff(d, dim=dim)  # n + 4 second differences
    t = torch.diff(dd, dim=dim)  # n + 3 third differences: the curvature of each pair (p, q) of dd

    def at(x: torch.Tensor, k: int) -> torch.Tensor:  # the n values from offset k
        return x.narrow(dim, k, n)

    # smoothness of each pair (p, q) = (dd_k, dd_k+1), k = 0 .. n+2, over 13: the curvature (q - p)^2
    # plus 3/13 of (p - 3q)^2 (Jiang & Peng's IS0 with (a, b) = (p, q)), (p + q)^2 (IS1) or
    # (3p - q)^2 (IS2)
    p, q = dd.narrow(dim, 0, n + 3), dd.narrow(dim, 1, n + 3)
    curvature = torch.mul(t, t).add_(12.0 / 13.0 * EPS * dx * dx)
    wa = _weight(curvature, torch.sub(p, q, alpha=3.0))
    wb = _weight(curvature, p + q)
    wc = _weight(curvature, torch.sub(q, p, alpha=3.0))
    e = torch.diff(t, dim=dim)  # n + 2 fourth differences a - 2b + c
    e_mid = at(e, 1)  # b - 2c + d of both biases
    # left bias at node j: (a, b, c, d) = dd_j .. dd_j+3, weights wa_j, 6 wb_j+1, 3 wc_j+2;
    # right bias: (a, b, c, d) = dd_j+4 .. dd_j+1, weights wc_j+3, 6 wb_j+2, 3 wa_j+1.
    # Each correction is Phi = X / 3 - e_mid / 12 with X = (w0 (a - 2b + c) + 1/2 w2 e_mid) / sum(w)
    num_left = torch.mul(at(wa, 0), at(e, 0)).addcmul_(at(wc, 2), e_mid, value=1.5)
    sum_left = torch.add(at(wa, 0), at(wb, 1), alpha=6.0).add_(at(wc, 2), alpha=3.0)
    num_right = torch.mul(at(wc, 3), at(e, 2)).addcmul_(at(wa, 1), e_mid, value=1.5)
    sum_right = torch.add(at(wc, 3), at(wb, 2), alpha=6.0).add_(at(wa, 1), alpha=3.0)
    # central part (-D1 + 7 D2 + 7 D3 - D4) / 12 of node j's differences D1..D4 = d_j+1 .. d_j+4,
    # kept as -12 times itself
    inner = torch.add(at(d, 2), at(d, 3))
    mean = torch.add(at(d, 1), at(d, 4)).add_(inner, alpha=-7.0)
    # mean = central + (X_R - X_L) / 6 and half jump = (X_R + X_L) / 6 - e_mid / 12, both times -12
    mean.addcdiv_(num_right, sum_right, value=-2.0).addcdiv_(num_left, sum_left, value=2.0)
    half_jump = torch.addcdiv(e_mid, num_right, sum_right, value=-2.0).addcdiv_(num_left, sum_left, value=-2.0)
    return mean, half_jump


def derivatives(v: torch.Tensor, dim: int, dx: float, periodic: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Left- and right-biased WENO5 approximations of ``dV/dx_dim`` at every node, times ``SCALE * dx``.

    For tests and inspection: the solver reads :func:`mean_and_half_jump` directly."""
    mean, half_jump = mean_and_half_jump(v, dim, dx, periodic)
    return mean - half_jump, mean + half_jump
