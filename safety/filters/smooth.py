"""The smooth filter (a control barrier-value function): the least change to the nominal input.

``SafetyFilter(vf, threshold, kind="smooth", gamma=gamma)`` applies the input closest to
``u_nominal`` (least squares) that satisfies the HJ barrier condition
``grad V . f(x, u, d*) + gamma (V - threshold) >= 0`` inside the input box (control barrier-value
functions, Choi et al. 2021). Where the switch jumps from the nominal input to the backup input at
the boundary, the smooth filter bends the nominal input only as much as the condition needs, so the
applied input changes gradually: the kind to use where chattering inputs matter (an actuator, a
passenger). ``gamma`` (1/s) is how fast ``V`` may fall towards the threshold; 0 forbids any decrease.

For control-affine systems the condition is one linear inequality in ``u``, so the problem is a
projection onto a half-space within a box, solved exactly and batched (the multiplier is found
between the kinks where inputs saturate; no QP solver). The control set must be a box (refused at
construction otherwise). Where no input of the box satisfies the condition, ``u*`` (the input that
does best) is applied and ``info.infeasible`` says so; that is also why its backup input defaults to
``u*`` (``policy="gradient"``): by definition the input that does best on its barrier condition. The
time-to-go is held fixed over the step (the fixed-horizon filter of the env adapters), so ``dV/dt``
drops out.

Reach kinds are refused at construction
(:func:`~safety.filters.settings.settings_for_system`): holding the time-to-go fixed is sound for
avoid's fixed-horizon tube, but a reach task has a deadline: the countdown puts ``dV/dt`` into the
condition (the value function gives no time derivative), and with ``t`` held fixed a car circling
inside ``{V(., T) < 0}`` meets the condition while the deadline passes.

Measured (chattering and collisions against the other kinds): docs/results/filters.md.
"""

from __future__ import annotations

import torch

from reach.systems.base import ControlAffineSystem
from reach.systems.box import require_box
from safety.filters.base import Evaluation, SafetyFilter

__all__ = ["SmoothFilter"]


class SmoothFilter(SafetyFilter, kind="smooth"):
    """The smooth filter (see the module docstring); made by ``SafetyFilter(vf, kind="smooth")``."""

    def _check_inputs(self, system: ControlAffineSystem) -> None:
        require_box(system.control_bounds, "the smooth filter (its projection is over a box)")

    def _choose(
        self, x: torch.Tensor, t: float | torch.Tensor, u_nominal: torch.Tensor, seen: Evaluation, trusted: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        value, p, u_star, d_star = seen
        applied, infeasible, keep = self._project(x, value, p, u_nominal, u_star, d_star)
        infeasible = infeasible & trusted
        keep = keep & trusted
        backup = ~trusted | infeasible
        applied = torch.where(backup.unsqueeze(-1), self._backup_input(x, t, u_star, d_star, backup), applied)
        return keep, applied, infeasible

    def _project(
        self,
        x: torch.Tensor,
        value: torch.Tensor,
        p: torch.Tensor,
        u_nominal: torch.Tensor,
        u_star: torch.Tensor,
        d_star: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """argmin |u - u_nom|^2 s.t. a . u >= b and u in the box, exactly, batched; returns the
        inputs, where the condition is infeasible, and where the nominal input already met it.

        ``p . f(x, u, d*)`` is affine in ``u`` with slope ``a = G_u^T p``; with ``f_c`` the dynamics
        at the box centre ``c``, the barrier condition reads ``a . u >= a . c - p . f_c - gamma (V - thr)``.
        The solution is ``clip(u_nom + lam a, box)`` for the smallest ``lam >= 0`` meeting it (the
        KKT conditions of a projection onto a half-space within a box); ``a . clip(u_nom + lam a)``
        is piecewise linear and non-decreasing in ``lam``, so it is solved exactly between two kinks.
        Infeasible where even ``u*`` (the box corner along ``a``) falls short."""
        system = self.system
        box = require_box(system.control_bounds, "the smooth filter (its projection is over a box)")
        dtype = torch.float64
        lo = torch.tensor(box.low, dtype=dtype, device=x.device)
        hi = torch.tensor(box.high, dtype=dtype, device=x.device)
        centre = torch.tensor(box.center, dtype=dtype, device=x.device)
        xd, pd = x.to(dtype), p.to(dtype)
        a = system.control_switching(xd, pd)
        f_centre = system.dynamics(xd, None, None if d_star is None else d_star.to(dtype))
        b = (a * centre).sum(-1) - (pd * f_centre).sum(-1) - self.gamma * (value.to(dtype) - self.threshold)
        u0 = u_nominal.to(dtype)
        ok_nominal = (a * u0).sum(-1) >= b
        best = (a * u_star.to(dtype)).sum(-1)
        infeasible = ~ok_nominal & (best < b)
        # g(lam) = a . clip(u_nom + lam a) is piecewise linear, with a kink where each input saturates:
        # evaluate it at the kinks and interpolate on the segment where it first reaches b
        toward = torch.where(a > 0, hi, lo)
        kinks = torch.where(a != 0, (toward - u0) / torch.where(a != 0, a, 1.0), 1e300).clamp(0.0, 1e300)
        lams = torch.cat([torch.zeros_like(kinks[..., :1]), kinks.sort(-1).values], -1)
        g = (a.unsqueeze(-2) * torch.clamp(u0.unsqueeze(-2) + lams.unsqueeze(-1) * a.unsqueeze(-2), lo, hi)).sum(-1)
        reached = g >= b.unsqueeze(-1)
        k = torch.where(reached.any(-1), reached.int().argmax(-1), lams.shape[-1] - 1).unsqueeze(-1)
        k_prev = (k - 1).clamp_min(0)
        lam_k, lam_p = lams.gather(-1, k), lams.gather(-1, k_prev)
        g_k, g_p = g.gather(-1, k), g.gather(-1, k_prev)
        step = torch.where(g_k > g_p, (b.unsqueeze(-1) - g_p) / (g_k - g_p).clamp_min(1e-300), 0.0)
        lam = torch.where(k == 0, 0.0, lam_p + step.clamp(0.0, 1.0) * (lam_k - lam_p))
        projected = torch.clamp(u0 + lam * a, lo, hi).to(u_star.dtype)
        applied = torch.where(ok_nominal.unsqueeze(-1), u_nominal, projected)
        applied = torch.where(infeasible.unsqueeze(-1), u_star, applied)
        return applied, infeasible, ok_nominal
