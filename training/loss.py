"""The HJI variational-inequality residual, with input gradients from autograd (reverse mode).

With ``t`` time-to-go, the value solves ``max(dV/dt - H(x, grad_x V), V - l(x)) = 0`` (REFERENCE.md
section 1). The residual is that left-hand side at sampled ``(x, t)``; the loss is its mean absolute
value (``l1``) or mean square (``l2``). The vanilla parameterisation adds a boundary term
``|V(x, 0) - l(x)|`` on the points sampled at ``t = 0``.
"""

from __future__ import annotations

import torch

from training.network import ValueNetwork


def hji_residual(network: ValueNetwork, x: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(residual, V)`` at states ``(N, n)`` and times ``(N,)``; keeps the graph for training."""
    x = x.requires_grad_(True)
    t = t.requires_grad_(True)
    v = network(x, t)
    dv_dx, dv_dt = torch.autograd.grad(v.sum(), (x, t), create_graph=True)
    system = network.system
    ham = system.hamiltonian(x, dv_dx)
    residual = torch.maximum(dv_dt - ham, v - system.failure_margin(x))
    return residual, v


def training_loss(
    network: ValueNetwork,
    x: torch.Tensor,
    t: torch.Tensor,
    *,
    norm: str = "l1",
    boundary_mask: torch.Tensor | None = None,
    boundary_weight: float = 1.0,
    pde: bool = True,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Scalar loss and its terms (``pde``, ``boundary``) as floats for logging."""
    terms: dict[str, float] = {}
    total = x.new_zeros(())
    if pde:
        residual, v = hji_residual(network, x, t)
        pde_loss = residual.abs().mean() if norm == "l1" else residual.square().mean()
        total = total + pde_loss
        terms["pde"] = float(pde_loss.detach())
    else:
        v = network(x, t)
    if network.parameterisation == "vanilla" and boundary_mask is not None and boundary_mask.any():
        gap = v[boundary_mask] - network.system.failure_margin(x[boundary_mask])
        boundary = gap.abs().mean() if norm == "l1" else gap.square().mean()
        total = total + boundary_weight * boundary
        terms["boundary"] = float(boundary.detach())
    terms["loss"] = float(total.detach())
    return total, terms
