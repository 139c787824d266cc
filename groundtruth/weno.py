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

import torch

EPS = 1e-6  # Jiang & Peng's epsilon in the nonlinear weights


def pad(v: torch.Tensor, dim: int, periodic: bool, width: int = 3) -> torch.Tensor:
    """``v`` with ``width`` ghost nodes on both sides of dimension ``dim``."""
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


#: :func:`derivatives` returns ``SCALE * dx`` times the one-sided derivatives; the caller folds the
#: factor into its own (one pass less over the grid for each of them)
SCALE = 3.0


def _weighted(phi1, phi2, phi3, w1, w2, w3, own_phi1: bool):
    """``(w1 phi1 + 6 w2 phi2 + 3 w3 phi3) / (w1 + 6 w2 + 3 w3)``: the WENO5 value of the stencils.

    The ``w`` are the nonlinear weights before their linear factors (see :func:`derivatives`); the
    linear weights 0.1, 0.6, 0.3 enter as 1 : 6 : 3 (their ratio is all that counts).
    ``own_phi1``: ``phi1`` is a temporary that may be overwritten.
    """
    num = phi1.mul_(w1) if own_phi1 else phi1 * w1
    num.addcmul_(phi2, w2, value=6.0).addcmul_(phi3, w3, value=3.0)
    return num.div_(torch.add(w1, w2, alpha=6.0).add_(w3, alpha=3.0))


def _weight(curvature: torch.Tensor, slope: torch.Tensor) -> torch.Tensor:
    """``1 / (curvature + 3/13 slope^2)^2``: a WENO5 nonlinear weight before its linear factor, up to a
    factor common to all three weights (see :func:`derivatives`)."""
    return torch.addcmul(curvature, slope, slope, value=3.0 / 13.0).pow_(-2)


def derivatives(v: torch.Tensor, dim: int, dx: float, periodic: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Left- and right-biased WENO5 approximations of ``dV/dx_dim`` at every node, times ``SCALE * dx``.

    The caller divides by ``SCALE * dx``, folded into its own factors. An eager solve is bound by
    passes over memory, so this is written for few of them:

    - the first differences stay undivided by ``dx``. Jiang & Peng's weights ``1 / (s + eps)^2`` then
      see ``s dx^2``, and ``eps dx^2`` in place of ``eps`` gives each weight times ``dx^4``;
    - each smoothness ``s = 13/12 (curvature^2 + 3/13 slope^2 + 12/13 eps)``, so the 13/12 and the
      ``eps`` go into the shared curvature once, and a common ``(12/13)^2`` multiplies every weight;
    - each smoothness indicator and weight is computed once on the padded line and read by both
      biases, and the two biases share two of their three candidate stencils (``phi2`` of one is
      ``phi3`` of the other);
    - the stencils are kept at half their usual ``6x`` scale, two passes each.

    Factors common to the three weights of a node cancel in their normalised combination, so the
    result is Jiang & Peng's to round-off (``tests/test_groundtruth.py`` checks it against the
    textbook formula in float64).
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
    wa = _weight(curvature, torch.sub(p, q, alpha=3.0))
    wb = _weight(curvature, p + q)
    wc = _weight(curvature, torch.sub(q, p, alpha=3.0))
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
