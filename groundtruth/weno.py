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


def _weighted(phi1, phi2, phi3, w1, w2, w3, own_phi1: bool):
    """``6 x`` the WENO5 value: ``(w1 phi1 + 6 w2 phi2 + 3 w3 phi3) / (w1 + 6 w2 + 3 w3)``.

    The ``w`` are the unnormalised weights ``1 / (s + eps)^2``; the linear weights 0.1, 0.6, 0.3 enter
    as 1 : 6 : 3 (their ratio is all that counts), and the stencils' common 1/6 is left to the caller.
    ``own_phi1``: ``phi1`` is a temporary that may be overwritten.
    """
    num = phi1.mul_(w1) if own_phi1 else phi1 * w1
    num.addcmul_(phi2, w2, value=6.0).addcmul_(phi3, w3, value=3.0)
    return num.div_(torch.add(w1, w2, alpha=6.0).add_(w3, alpha=3.0))


def _weight(curvature: torch.Tensor, slope: torch.Tensor) -> torch.Tensor:
    """``1 / (s + eps)^2`` for the smoothness ``s = curvature + slope^2 / 4``: a WENO5 nonlinear
    weight before its linear factor."""
    return torch.addcmul(curvature, slope, slope, value=0.25).add_(EPS).square_().reciprocal_()


def derivatives(v: torch.Tensor, dim: int, dx: float, periodic: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Left- and right-biased WENO5 approximations of ``dV/dx_dim`` at every node, times 6.

    The caller divides by 6 (folded into its own factors: one pass less over the grid). Written for
    few passes over memory, since an eager solve is bound by them: each smoothness indicator and
    nonlinear weight is computed once on the padded line and read by both biases, and the two
    biases share two of their three candidate stencils (``phi2`` of one is ``phi3`` of the other).
    """
    n = v.shape[dim]
    d = torch.diff(pad(v, dim, periodic), dim=dim).div_(dx)  # n + 5 first differences D
    dd = torch.diff(d, dim=dim)  # n + 4 second differences: D_{k+1} - D_k

    def at(x: torch.Tensor, k: int, length: int) -> torch.Tensor:
        return x.narrow(dim, k, length)

    # Jiang-Peng smoothness of each triple (a, b, c) = (D_k, D_k+1, D_k+2), k = 0 .. n+2: the curvature
    # 13/12 (a - 2b + c)^2 plus 1/4 of (a - 4b + 3c)^2, (a - c)^2 or (3a - 4b + c)^2. With the second
    # differences p = b - a and q = c - b: a - 2b + c = q - p, a - 4b + 3c = -(p - 3q),
    # a - c = -(p + q), 3a - 4b + c = q - 3p.
    p, q = at(dd, 0, n + 3), at(dd, 1, n + 3)
    curvature = (q - p).square_().mul_(13.0 / 12.0)
    wa = _weight(curvature, torch.sub(p, q, alpha=3.0))
    wb = _weight(curvature, p + q)
    wc = _weight(curvature, torch.sub(q, p, alpha=3.0))
    D = [at(d, k, n) for k in range(6)]
    # candidate stencils (times 6): phi1, phi2, phi3 of the left bias read D_0..D_4, the right bias
    # reads D_5..D_1 backwards, so its phi2 and phi3 are the left bias's phi3 and phi2
    left1 = (2.0 * D[0]).sub_(D[1], alpha=7.0).add_(D[2], alpha=11.0)
    middle_left = (5.0 * D[2]).sub_(D[1]).add_(D[3], alpha=2.0)
    middle_right = (5.0 * D[3]).sub_(D[4]).add_(D[2], alpha=2.0)
    right1 = (2.0 * D[5]).sub_(D[4], alpha=7.0).add_(D[3], alpha=11.0)
    left = _weighted(left1, middle_left, middle_right, at(wa, 0, n), at(wb, 1, n), at(wc, 2, n), True)
    right = _weighted(right1, middle_right, middle_left, at(wc, 3, n), at(wb, 2, n), at(wa, 1, n), True)
    return left, right
