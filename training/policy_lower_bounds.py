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

:func:`mpc_lower_bound` is the sampling-based variant after DeepReach-MPC: the best of several
perturbed control sequences over a short horizon, bootstrapped by the network's own value at its
end (a dynamic-programming consistency rather than a bound of the true value).
"""

from __future__ import annotations

import math

import torch

from reach.integrators import make_stepper
from reach.systems.arrays import TORCH
from reach.systems.base import ControlAffineSystem
from reach.systems.box import require_box
from reach.validation import check_float, positive_finite
from training.network import NeuralValueFunction, ValueNetwork


def check_lower_bound_system(system: ControlAffineSystem) -> None:
    """Refuse, before training, a system whose policy rollouts bound nothing or miss dips of ``l``."""
    # a reach kind's policy rollout bounds the value from above (the control minimises), not below
    system.require_kind(("avoid",), "lower_bound labels")
    if system.disturbance_dim:
        raise ValueError(
            f"lower_bound: {system.name} has a disturbance, and a rollout against a model "
            "disturbance is no lower bound of the value; use it for systems without one"
        )
    probe = system.sample_states(1, torch.Generator().manual_seed(0))
    if system.margin_floor(probe, 0.01) is None:
        raise ValueError(
            f"lower_bound: {system.name} declares no bound on how fast l can fall "
            "(margin_rate_bound or margin_floor), so dips of l between steps could be missed"
        )


def _check_dt(dt: float) -> None:
    positive_finite("dt", dt)


def _closed_loop(
    network: ValueNetwork,
    x: torch.Tensor,
    t: torch.Tensor,
    duration: torch.Tensor,
    dt: float,
    noise: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Roll each state out under the network's ``u*`` (plus ``noise[k]`` times the box's half-width at
    step ``k``, clipped to the box) for whole steps of ``dt`` covering its ``duration``.

    Returns the lowest margin floor along the way (``l`` itself for a zero duration), the final
    states and the times-to-go left there (``t`` minus the simulated time, negative when it overran).
    """
    system = network.system
    _check_dt(dt)
    value_function = NeuralValueFunction(network)
    advance = make_stepper(system, dt, "rk4", TORCH)
    box = require_box(system.control_bounds, "policy lower-bound labels (their noisy inputs are clipped to the box)")
    centre, half = (torch.tensor(v, dtype=x.dtype, device=x.device) for v in (box.center, box.half_width))
    x = x.detach().clone()
    t, duration = t.detach(), duration.detach()
    lowest = system.failure_margin(x)
    steps = math.ceil(float(duration.max()) / dt - 1e-9) if duration.numel() else 0
    simulated = torch.zeros_like(t)
    with torch.no_grad():
        for k in range(steps):
            rows = torch.nonzero(duration - k * dt > 0).squeeze(-1)
            if rows.numel() == 0:
                break
            xa = x[rows]
            lowest[rows] = torch.minimum(lowest[rows], system.margin_floor(xa, dt))
            _, p = value_function.value_and_gradient(xa, (t[rows] - k * dt).clamp(0.0, system.horizon))
            u = system.optimal_control(xa, p)
            if noise is not None:
                u = torch.minimum(torch.maximum(u + noise[k, rows] * half, centre - half), centre + half)
            cols = TORCH.unbind(xa)
            x[rows] = TORCH.stack(advance(cols, TORCH.unbind(u), system.disturbance_bounds.center), like=cols[0])
            simulated[rows] += dt
    return lowest, x, t - simulated


def policy_lower_bound(network: ValueNetwork, x: torch.Tensor, t: torch.Tensor, dt: float) -> torch.Tensor:
    """``J(x, t) <= V(x, t)`` for states ``(N, n)`` and times-to-go ``(N,)``: see the module docstring."""
    lowest, _, _ = _closed_loop(network, x, t, t, dt)
    return lowest


def mpc_lower_bound(
    network: ValueNetwork,
    x: torch.Tensor,
    t: torch.Tensor,
    dt: float,
    horizon: float,
    samples: int,
    noise: float,
    generator: torch.Generator,
) -> torch.Tensor:
    """Sampling-based MPC labels bootstrapped by the network (after DeepReach-MPC).

    From each state, ``samples`` control sequences run for ``min(t, horizon)`` seconds: the
    network's ``u*`` and ``samples - 1`` perturbations of it (Gaussian, ``noise`` times the box's
    half-width, clipped to the box). Each scores ``min(lowest margin floor, V_net(x_H, t - H))``,
    and the label is the best score. For the true value, dynamic programming gives
    ``V(x, t) >= min(min l, V(x_H, t - H))`` under any control, so the term asks the network to be
    consistent with its own values ``H`` seconds on (where ``t <= horizon`` no network value enters,
    and the label is a lower bound of the true value as :func:`policy_lower_bound`'s is).
    """
    _check_dt(dt)  # before the step count below divides by it
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples must be a positive integer, got {samples!r}")
    positive_finite("horizon", horizon)
    check_float("noise", noise, 0)
    n, m = x.shape[0], network.system.control_dim
    xs, ts = x.repeat(samples, 1), t.repeat(samples)
    duration = ts.clamp(max=horizon)
    steps = max(1, math.ceil(horizon / dt - 1e-9))
    eps = torch.randn((steps, samples * n, m), generator=generator, device=x.device, dtype=x.dtype) * noise
    eps[:, :n] = 0.0  # the first sample is the network's own policy
    lowest, x_end, left = _closed_loop(network, xs, ts, duration, dt, eps)
    ahead = left > 0
    if bool(ahead.any()):
        with torch.no_grad():
            terminal = NeuralValueFunction(network).value(x_end[ahead], left[ahead])
        lowest[ahead] = torch.minimum(lowest[ahead], terminal.to(lowest.dtype))
    return lowest.reshape(samples, n).max(dim=0).values
