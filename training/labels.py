"""Lower-bound labels for training: what the network's own policy provably achieves.

For a system without a disturbance (the cooperative multi-vehicle systems), any control law gives
a lower bound of the true value: ``V(x, t) = max_u min_s l(x(s))`` is at least what one particular
``u`` achieves. :func:`policy_lower_bound` rolls out the network's optimal policy ``u*`` (the box
corner along ``G^T grad V``, held over steps of ``dt``) from sampled states and returns

    J(x, t) = min over the steps of margin_floor(x_k, dt)

where ``margin_floor`` (:meth:`~reach.systems.base.ControlAffineSystem.margin_floor`) bounds ``l``
from below over a step under any inputs, so dips of ``l`` between steps count. The steps use RK4
with the inputs held (``reach.integrators``): up to RK4's truncation error (``O(dt^4)``), the
trajectory is that of a real sample-and-hold controller, and ``J <= V``. Every row is simulated for
whole steps up to ``ceil(t / dt) dt >= t``; a longer horizon can only lower ``J``, so it stays a
lower bound.

Training adds ``lower_bound_weight * mean(relu(J - V))``: ``V`` may not sit below what its own
policy shows is achievable, which the PDE residual alone does not enforce (DeepReach's
cost-supervised learning, as a one-sided constraint). A system with a disturbance is refused: a
rollout against a model disturbance bounds nothing.
"""

from __future__ import annotations

import math

import torch

from reach.integrators import make_stepper
from reach.systems.backend import TORCH
from reach.systems.base import ControlAffineSystem
from training.network import NeuralValueFunction, ValueNetwork


def check_lower_bound_system(system: ControlAffineSystem) -> None:
    """Refuse, before training, a system whose policy rollouts bound nothing or miss dips of ``l``."""
    if system.disturbance_dim:
        raise ValueError(
            f"lower_bound='policy': {system.name} has a disturbance, and a rollout against a model "
            "disturbance is no lower bound of the value; use it for systems without one"
        )
    probe = system.sample_states(1, torch.Generator().manual_seed(0))
    if system.margin_floor(probe, 0.01) is None:
        raise ValueError(
            f"lower_bound='policy': {system.name} declares no bound on how fast l can fall "
            "(margin_rate_bound or margin_floor), so dips of l between steps could be missed"
        )


def policy_lower_bound(network: ValueNetwork, x: torch.Tensor, t: torch.Tensor, dt: float) -> torch.Tensor:
    """``J(x, t) <= V(x, t)`` for states ``(N, n)`` and times-to-go ``(N,)``: see the module docstring."""
    system = network.system
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be positive and finite, got {dt!r}")
    value_function = NeuralValueFunction(network)
    advance = make_stepper(system, dt, "rk4", TORCH)
    x = x.detach().clone()
    t = t.detach()
    bound = system.failure_margin(x)  # t = 0: V = l
    steps = math.ceil(float(t.max()) / dt - 1e-9) if t.numel() else 0
    with torch.no_grad():
        for k in range(steps):
            left = t - k * dt
            rows = torch.nonzero(left > 0).squeeze(-1)
            if rows.numel() == 0:
                break
            xa = x[rows]
            bound[rows] = torch.minimum(bound[rows], system.margin_floor(xa, dt))
            _, p = value_function.value_and_gradient(xa, left[rows].clamp(max=system.horizon))
            u = system.optimal_control(xa, p)
            cols = TORCH.unbind(xa)
            x[rows] = TORCH.stack(advance(cols, TORCH.unbind(u), system.disturbance_bounds.center), like=cols[0])
    return bound
