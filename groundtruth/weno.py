"""Upwind HJ-WENO5 derivatives (Jiang & Peng 2000) along one grid dimension, batched over the grid.

For node ``i`` the left-biased derivative uses the five one-sided differences
``D_{i-3} .. D_{i+1}`` (``D_k = (V_{k+1} - V_k) / dx``) and the right-biased one ``D_{i+2} .. D_{i-2}``.
Both read the same three smoothness indicators of each triple of consecutive differences, so they are
computed once for the whole padded line and sliced: this halves the work of a naive implementation.

Two forms give the same values to round-off: :func:`mean_and_half_jump` (Jiang & Peng's central
part plus corrections, the fewest passes over memory, for eager solves) and
:func:`biased_derivatives` (the one-sided stencils, for solves under ``torch.compile``, where the
arithmetic counts instead). The solver calls the first, which hands over to the second when compiling.

Boundaries: periodic dimensions wrap; other dimensions are padded with three ghost nodes that
*extrapolate away from zero* (``V_edge + sign(V_edge) |V_edge - V_inner| k``), so that the zero level
set never enters from the box edge.
"""

from __future__ import annotations

import torch

EPS = 1e-6  # Jiang & Peng's epsilon in the nonlinear weights


def pad(v: torch.Tensor, dim: int, periodic: bool, width: int = 3) -> torch.Tensor:
    """``v`` with ``width`` ghost nodes on both sides of dimension ``dim`` (the form compiled solves
    difference; eager solves difference without it, :func:`padded_differences`)."""
    n = v.shape[dim]
    if periodic:
        return torch.cat([v.narrow(dim, n - width, width), v, v.narrow(dim, 0, width)], dim)
    shape = [1] * v.ndim
    shape[dim] = width
    k = torch.arange(1, width + 1, dtype=v.dtype, device=v.device).reshape(shape)
    first, second = v.narrow(dim, 0, 1), v.narrow(dim, 1, 1)
    last, before = v.narrow(dim, n - 1, 1), v.narrow(dim, n - 2, 1)
    left = first + torch.sign(first) * (second - first).abs() * k.flip(dim)
    right = last + torch.sign(last) * (last - before).abs() * k
    return torch.cat([left, v, right], dim)


def padded_differences(v: torch.Tensor, dim: int, periodic: bool, width: int = 3) -> torch.Tensor:
    """``torch.diff(pad(v, dim, periodic, width), dim=dim)`` without forming the padded copy.

    The ``n + 2 width - 1`` first differences are written into one buffer: the ``n - 1`` interior
    ones straight from ``v``, then the ghost ones, which need no ghost node. Periodic, they are the
    wrap-around difference and copies of interior ones. Extrapolated away from zero, every ghost
    difference at an end equals the edge's: ``-sign(V_0) |V_1 - V_0|`` on the left and
    ``sign(V_n-1) |V_n-1 - V_n-2|`` on the right. An eager solve is bound by passes over memory, and
    the padded copy was one full pass per dimension and stage, plus the gathers that filled its
    ghosts (measured: docs/results/groundtruth.md, *No padded copy*)."""
    n = v.shape[dim]
    shape = list(v.shape)
    shape[dim] = n + 2 * width - 1
    d = v.new_empty(shape)
    torch.sub(v.narrow(dim, 1, n - 1), v.narrow(dim, 0, n - 1), out=d.narrow(dim, width, n - 1))
    if periodic:  # d holds the cyclic differences from offset width; the ghosts repeat their ends
        torch.sub(v.narrow(dim, 0, 1), v.narrow(dim, n - 1, 1), out=d.narrow(dim, width + n - 1, 1))
        d.narrow(dim, 0, width).copy_(d.narrow(dim, n, width))
        d.narrow(dim, width + n, width - 1).copy_(d.narrow(dim, width, width - 1))
        return d
    left = d.narrow(dim, width, 1).abs().mul_(v.narrow(dim, 0, 1).sign()).neg_()
    right = d.narrow(dim, width + n - 2, 1).abs().mul_(v.narrow(dim, n - 1, 1).sign())
    d.narrow(dim, 0, width).copy_(left)
    d.narrow(dim, width + n - 1, width).copy_(right)
    return d


#: :func:`mean_and_half_jump` returns ``SCALE * dx`` times the mean and the half jump of the two
#: one-sided derivatives; the caller folds the factor into its own (one pass less over the grid each)
SCALE = -12.0


def _weight(curvature: torch.Tensor, slope: torch.Tensor) -> torch.Tensor:
    """``1 / (curvature + 3/13 slope^2)^2``: a WENO5 nonlinear weight before its linear factor, up to a
    factor common to all three weights (see :func:`mean_and_half_jump`)."""
    return torch.addcmul(curvature, slope, slope, value=3.0 / 13.0).pow_(-2)


def _weights(
    curvature: torch.Tensor, p: torch.Tensor, q: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The weights of each pair ``(p, q)`` of consecutive second differences, for Jiang & Peng's
    slopes ``p - 3q`` (their IS0), ``p + q`` (IS1) and ``q - 3p`` (IS2); both forms read them."""
    return (
        _weight(curvature, torch.sub(p, q, alpha=3.0)),
        _weight(curvature, p + q),
        _weight(curvature, torch.sub(q, p, alpha=3.0)),
    )


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
    if torch.compiler.is_compiling():
        left, right = biased_derivatives(v, dim, dx, periodic)
        return (left + right) * (SCALE / (2.0 * BIASED_SCALE)), (right - left) * (SCALE / (2.0 * BIASED_SCALE))
    n = v.shape[dim]
    d = padded_differences(v, dim, periodic)  # n + 5 first differences, times dx
    dd = torch.diff(d, dim=dim)  # n + 4 second differences
    t = torch.diff(dd, dim=dim)  # n + 3 third differences: the curvature of each pair (p, q) of dd

    def at(x: torch.Tensor, k: int) -> torch.Tensor:  # the n values from offset k
        return x.narrow(dim, k, n)

    # smoothness of each pair (p, q) = (dd_k, dd_k+1), k = 0 .. n+2, over 13: the curvature (q - p)^2
    # plus 3/13 of (p - 3q)^2 (Jiang & Peng's IS0 with (a, b) = (p, q)), (p + q)^2 (IS1) or
    # (3p - q)^2 (IS2)
    p, q = dd.narrow(dim, 0, n + 3), dd.narrow(dim, 1, n + 3)
    floor = torch.tensor(12.0 / 13.0 * EPS * dx * dx, dtype=t.dtype)  # a CPU scalar serves any device
    curvature = torch.addcmul(floor, t, t)  # one pass, not a product and then a sum
    wa, wb, wc = _weights(curvature, p, q)
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


#: :func:`biased_derivatives` returns ``BIASED_SCALE * dx`` times the one-sided derivatives
BIASED_SCALE = 3.0


def _weighted(phi1, phi2, phi3, w1, w2, w3, own_phi1: bool):
    """``(w1 phi1 + 6 w2 phi2 + 3 w3 phi3) / (w1 + 6 w2 + 3 w3)``: the WENO5 value of the stencils.

    The ``w`` are the nonlinear weights before their linear factors (see :func:`biased_derivatives`); the
    linear weights 0.1, 0.6, 0.3 enter as 1 : 6 : 3 (their ratio is all that counts).
    ``own_phi1``: ``phi1`` is a temporary that may be overwritten.
    """
    num = phi1.mul_(w1) if own_phi1 else phi1 * w1
    num.addcmul_(phi2, w2, value=6.0).addcmul_(phi3, w3, value=3.0)
    return num.div_(torch.add(w1, w2, alpha=6.0).add_(w3, alpha=3.0))


def biased_derivatives(v: torch.Tensor, dim: int, dx: float, periodic: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Left- and right-biased WENO5 approximations of ``dV/dx_dim`` at every node, times ``BIASED_SCALE * dx``.

    The form :func:`mean_and_half_jump` takes under ``torch.compile``: fused into a few kernels,
    passes over memory cost little, and what counts is the arithmetic and the buffers the compiler
    keeps. Compiled, Jiang & Peng's form (which divides twice per bias and keeps two more difference
    arrays) with the eager padding ran a right-hand side slower than this form; eager, this one is
    the slower (measured: docs/results/groundtruth.md, *Eager speed*). It is built from the one-sided
    stencils:

    - the first differences stay undivided by ``dx``. Jiang & Peng's weights ``1 / (s + eps)^2`` then
      see ``s dx^2``, and ``eps dx^2`` in place of ``eps`` gives each weight times ``dx^4``;
    - each smoothness ``s = 13/12 (curvature^2 + 3/13 slope^2 + 12/13 eps)``, so the 13/12 and the
      ``eps`` go into the shared curvature once, and a common ``(12/13)^2`` multiplies every weight;
    - each smoothness indicator and weight is computed once on the padded line and read by both
      biases, and the two biases share two of their three candidate stencils (``phi2`` of one is
      ``phi3`` of the other);
    - the stencils are kept at half their usual ``6x`` scale, two passes each.

    Factors common to the three weights of a node cancel in their normalised combination, so the
    result is Jiang & Peng's to round-off (``tests/test_groundtruth.py`` checks both forms against
    the textbook formula in float64).
    """
    n = v.shape[dim]
    d = torch.diff(pad(v, dim, periodic), dim=dim)  # n + 5 first differences D, times dx
    dd = torch.diff(d, dim=dim)  # n + 4 second differences: D_{k+1} - D_k

    def at(x: torch.Tensor, k: int, length: int) -> torch.Tensor:
        return x.narrow(dim, k, length)

    # Jiang-Peng smoothness of each triple (a, b, c) = (D_k, D_k+1, D_k+2), k = 0 .. n+2: the curvature
    # 13/12 (a - 2b + c)^2 plus 1/4 of (a - 4b + 3c)^2, (a - c)^2 or (3a - 4b + c)^2. With the second
    # differences p = b - a and q = c - b: a - 2b + c = q - p, a - 4b + 3c = -(p - 3q),
    # a - c = -(p + q), 3a - 4b + c = q - 3p.
    p, q = at(dd, 0, n + 3), at(dd, 1, n + 3)
    curvature = (q - p).square_().add_(12.0 / 13.0 * EPS * dx * dx)
    wa, wb, wc = _weights(curvature, p, q)
    D = [at(d, k, n) for k in range(6)]
    # candidate stencils (times 3): phi1, phi2, phi3 of the left bias read D_0..D_4, the right bias
    # reads D_5..D_1 backwards, so its phi2 and phi3 are the left bias's phi3 and phi2
    left1 = torch.add(D[0], D[1], alpha=-3.5).add_(D[2], alpha=5.5)
    middle_left = torch.add(D[3], D[1], alpha=-0.5).add_(D[2], alpha=2.5)
    middle_right = torch.add(D[2], D[4], alpha=-0.5).add_(D[3], alpha=2.5)
    right1 = torch.add(D[5], D[4], alpha=-3.5).add_(D[3], alpha=5.5)
    left = _weighted(left1, middle_left, middle_right, at(wa, 0, n), at(wb, 1, n), at(wc, 2, n), True)
    right = _weighted(right1, middle_right, middle_left, at(wc, 3, n), at(wb, 2, n), at(wa, 1, n), True)
    return left, right
