"""The lookahead filter (a backup shield): keep the nominal input only where the next step is safe.

``SafetyFilter(vf, threshold, kind="lookahead", dt=dt)`` predicts the state one step ``dt`` ahead
under ``u_nominal`` (the system's own integrator, inputs held over the step), then rolls the backup
policy forward from there for ``backup_horizon`` seconds (default: the system's horizon, the time the
BRT speaks for), and keeps ``u_nominal`` only if ``min(V, l)`` stays above ``threshold`` at every
predicted state; else it applies the backup input (or the control box's centre where the backup
input fails the same check and the centre passes it: :meth:`LookaheadFilter._fallback`).

Use it where a state must not ride the boundary between two decisions: it judges what the step does,
not where the state is, so its default threshold is 0 where the switch's is a margin
(:mod:`safety.filters.switch`); each decision rolls up to ``backup_horizon / dt`` backup steps, one
value-and-gradient evaluation each, where the switch evaluates once (measured:
docs/results/filters.md). Checking one step of ``u*`` alone is not enough at threshold 0: near the
BRT's edge a held ``u*`` loses a little value each step, and states ride the failure set's edge into
a graze; the backup rollout is what rules that out.

``backup_disturbance="robust"`` (default) checks two predicted paths: the value function's ``d*``,
and a greedy worst case that each step takes whichever of ``d*`` and the disturbance box's corners
leaves the least ``min(V, l)`` (the real disturbance need not be the model's ``d*``, e.g. a pursuer
steered by another value function); ``"model"`` checks the first alone.

The backup input defaults to ``u*`` (``policy="gradient"``): the lookahead verifies its backup
rollout before it relies on it, and with the greedy input every backup step would cost
``2^m_u + 1`` value evaluations instead of one.

Reach kinds (``"reach"``, ``"reach-avoid"``; :mod:`safety.filters.base`): the lookahead keeps
``u_nominal`` where the state one step ahead has ``V(y, t - dt) < -threshold`` and the backup
rollout of ``u*`` after it keeps ``min(-V, g) > threshold`` (``-V`` alone for reach) until it
reaches the target (``l < 0`` and ``g > 0``: the task is done there, and the path stops) or its
time-to-go runs out; else ``u*`` (or the centre, as for avoid). A predicted state outside the domain
certifies nothing (``-inf``). The predictions are evaluated at ``t - dt``, ``t - 2 dt``, ... (floored
at 0); where less than one step ``dt`` of time-to-go is left (the nominal step would end past the
deadline) nothing can be certified and ``u*`` is applied. For avoid the predictions are evaluated at
``t`` itself (the fixed horizon of the env adapters; avoid's tube value only falls as ``t`` grows, so
holding ``t`` is the cautious side).
"""

from __future__ import annotations

import math

import torch

from reach.integrators import check_integrator, make_stepper
from reach.systems.arrays import TORCH
from reach.systems.base import ControlAffineSystem
from reach.systems.box import require_box
from safety.filters.base import Evaluation, SafetyFilter
from safety.filters.settings import MAX_BACKUP_STEPS
from safety.tracing import tracing

__all__ = ["LookaheadFilter"]


class LookaheadFilter(SafetyFilter, kind="lookahead"):
    """The lookahead filter (see the module docstring); made by
    ``SafetyFilter(vf, kind="lookahead", dt=dt)``.

    :meth:`step_ahead` (one predicted step) and :meth:`backup_holds` (the check of one input) are
    the two parts of its decision, public for the studies and tests that look inside it."""

    def _backup_steps(self, system: ControlAffineSystem, dt: float | None, integrator: str, horizon: float) -> int:
        """Enough held steps of ``dt`` to cover ``horizon``, at most :data:`MAX_BACKUP_STEPS`; the
        stepper that predicts them, made once."""
        if dt is None:
            raise ValueError("the lookahead filter needs a step dt > 0, got None")
        self._stepper = make_stepper(system, dt, check_integrator(integrator), TORCH)
        steps = math.ceil(horizon / dt - 1e-9)
        if steps > MAX_BACKUP_STEPS:
            raise ValueError(
                f"backup_horizon {horizon:g} s at dt {dt:g} s is {steps} backup steps per decision; "
                f"at most {MAX_BACKUP_STEPS} (lower backup_horizon or raise dt)"
            )
        return steps

    def _choose(
        self, x: torch.Tensor, t: float | torch.Tensor, u_nominal: torch.Tensor, seen: Evaluation, trusted: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, None]:
        u_star, d_star = seen.u_star, seen.d_star
        if tracing():
            keep, applied = self._every_row(x, t, u_nominal, u_star, d_star, trusted)
            return keep, applied, None
        keep = self.backup_holds(x, t, u_nominal, d_star) & trusted
        u_back = self._backup_input(x, t, u_star, d_star, ~keep)
        return keep, torch.where(keep.unsqueeze(-1), u_nominal, self._fallback(x, t, u_back, d_star, ~keep)), None

    def step_ahead(self, x: torch.Tensor, u: torch.Tensor, d: torch.Tensor | None) -> torch.Tensor:
        """The state one step ``dt`` ahead under ``u`` and ``d`` held over the step (the filter's
        integrator)."""
        system = self.system
        cols = TORCH.unbind(x)
        uc = system.input_columns(u, system.control_bounds, "u")
        dc = system.input_columns(d, system.disturbance_bounds, "d")
        return TORCH.stack(self._stepper(cols, uc, dc), like=cols[0])

    def backup_holds(
        self, x: torch.Tensor, t: float | torch.Tensor, u: torch.Tensor, d_star: torch.Tensor | None
    ) -> torch.Tensor:
        """Where ``min(V, l)`` stays above the threshold over one step under ``u`` and the backup
        rollout after it, along every predicted disturbance path (the lookahead's decision, on inputs
        :meth:`~safety.filters.base.SafetyFilter.__call__` has checked; ``d_star`` is ``d*`` at ``x``,
        None without a disturbance). Reach kinds:
        ``min(-V, g)`` at the counted-down time-to-go, each path stopping at the target or when its
        time-to-go runs out, and nothing holds where less than one step ``dt`` of it is left
        (:meth:`_safety_value`, :meth:`_after`).

        Both paths (``d*``, and the greedy worst case when robust) roll in one batch: per backup step
        one value-and-gradient evaluation, plus one value evaluation of the greedy path's candidates.
        A predicted state outside the system's domain has no trusted ``V`` (a grid raises there): its
        ``l`` counts and its rollout stops (the backup has carried it out of the region ``V``
        speaks for; for the built-in systems that is away from the failure set)."""
        system = self.system
        n = system.state_dim
        batch = x.shape[:-1]
        x = x.reshape(-1, n)
        enough = self._time_left(t, self.dt, x[:, 0])  # reach kinds: a whole step before the deadline
        paths = 2 if self.backup_disturbance == "robust" and system.disturbance_dim > 0 else 1
        start = x.repeat(paths, 1)
        greedy = x.shape[0] if paths == 2 else None  # the second half of the batch takes the greedy worst case
        d = None if d_star is None else d_star.reshape(-1, system.disturbance_dim).repeat(paths, 1)
        domain = system.domain_tensor(x.dtype, x.device)
        if isinstance(t, torch.Tensor) and t.ndim:  # per-state times-to-go follow their states
            t = t.reshape(-1).expand(x.shape[0]).repeat(paths)
        u_start = u.reshape(-1, system.control_dim).repeat(paths, 1)
        y = self._predict(start, u_start, d, greedy, domain, self._after(t, 1))
        low = torch.full((start.shape[0],), math.inf, dtype=x.dtype, device=x.device)
        stopped = torch.zeros(start.shape[0], dtype=torch.bool, device=x.device)
        for k in range(self.backup_steps + 1):
            tk = self._after(t, k + 1)  # the predicted state's time-to-go (held for avoid)
            inside = self._inside(y, domain)
            y_in = torch.where(inside.unsqueeze(-1), y, start)  # states rolled out of the domain idle
            if k < self.backup_steps:
                v, _, u_back, d_back = self._evaluate(y_in, tk)
                u_back = self._backup_input(y_in, tk, u_back, d_back, ~stopped & inside)
            else:  # the rollout's last state: its value alone
                v = self.value_function.value(y_in, tk)
                self._trust(y_in, tk, v, None, None)
            low = torch.where(stopped, low, torch.minimum(low, self._safety_value(v, y, inside)))
            # a state fails once any of its paths has: its verdict is decided, its rollouts stop
            failed = (low <= self.threshold).reshape(paths, -1).any(0).repeat(paths)
            stopped = stopped | ~inside | self._finished(y, tk) | failed
            if k == self.backup_steps or (not tracing() and bool(stopped.all())):
                break  # a graph rolls every step (stopped paths idle: their verdict is kept)
            y = torch.where(
                inside.unsqueeze(-1), self._predict(y_in, u_back, d_back, greedy, domain, self._after(t, k + 2)), y
            )
        # a NaN compares False: "not above" keeps no nominal input (and _trust refuses it first)
        return ((low.reshape(paths, -1).amin(0) > self.threshold) & enough).reshape(batch)

    def _fallback(
        self,
        x: torch.Tensor,
        t: float | torch.Tensor,
        u_star: torch.Tensor,
        d_star: torch.Tensor | None,
        needed: torch.Tensor,
    ) -> torch.Tensor:
        """The lookahead's input where the nominal one failed: ``u*``, unless ``u*`` itself fails the
        backup check and the control box's centre passes it.

        On a singular arc the switching function of ``u*`` is near zero and a sampled ``u*`` flips
        between box corners from step to step, losing a little ``l`` with every held corner; the centre
        is the candidate that does not chatter (measured: docs/results/filters.md). Only the states that
        need a fallback are checked again.
        """
        fallback = u_star.clone()
        m = self.system.control_dim
        centre = torch.tensor(self.system.control_bounds.center, dtype=u_star.dtype, device=u_star.device)
        if not bool(needed.any()):
            return fallback
        rows = torch.nonzero(needed.reshape(-1)).squeeze(-1)
        xs, ts, ds = self._rows(rows, x, t, d_star)
        us = u_star.reshape(-1, m)[rows]
        failing = ~self.backup_holds(xs, ts, us, ds)
        if not bool(failing.any()):
            return fallback
        rows, xs, us = rows[failing], xs[failing], us[failing]  # only where u* fails is the centre checked
        ts = ts[failing] if isinstance(ts, torch.Tensor) and ts.ndim else ts
        ds = None if ds is None else ds[failing]
        centre = centre.expand_as(us)
        use_centre = self.backup_holds(xs, ts, centre, ds)
        flat = fallback.reshape(-1, m)
        flat[rows[use_centre]] = centre[use_centre]
        return flat.reshape(u_star.shape)

    def _every_row(
        self,
        x: torch.Tensor,
        t: float | torch.Tensor,
        u_nominal: torch.Tensor,
        u_star: torch.Tensor,
        d_star: torch.Tensor | None,
        trusted: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The lookahead's decision as a graph computes it (:mod:`safety.tracing`): the nominal input,
        the backup input and the control box's centre are checked for every row in one batched
        backup rollout, where the eager path checks the backup input and then the centre only on
        the rows that need them (:meth:`_fallback`). The same verdict per row: ``(keep, applied)``."""
        flat_x = x.reshape(-1, self.system.state_dim)
        rows = flat_x.shape[0]
        every = torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)
        u_back = self._backup_input(x, t, u_star, d_star, every)
        centre = torch.tensor(self.system.control_bounds.center, dtype=u_star.dtype, device=u_star.device)
        m = self.system.control_dim
        candidates = torch.cat([u_nominal.reshape(-1, m), u_back.reshape(-1, m), centre.expand(rows, m)])
        tt = t.reshape(-1).expand(rows).repeat(3) if isinstance(t, torch.Tensor) and t.ndim else t
        dd = None if d_star is None else d_star.reshape(rows, -1).repeat(3, 1)
        holds = self.backup_holds(flat_x.repeat(3, 1), tt, candidates, dd).reshape(3, *x.shape[:-1])
        keep = holds[0] & trusted
        fallback = torch.where((~holds[1] & holds[2]).unsqueeze(-1), centre, u_back)
        return keep, torch.where(keep.unsqueeze(-1), u_nominal, fallback)

    def _predict(
        self,
        x: torch.Tensor,
        u: torch.Tensor,
        d: torch.Tensor | None,
        greedy: int | None,
        domain: torch.Tensor,
        t: float | torch.Tensor,
    ) -> torch.Tensor:
        """The predicted next states under ``u``: under ``d``, and on the rows from ``greedy`` on
        (None: no row) under whichever of ``d`` and the disturbance box's corners leaves the least
        ``min(V, l)``."""
        y = self.step_ahead(x, u, d)
        if d is None or greedy is None:
            return y
        system = self.system
        box = require_box(system.disturbance_bounds, "the lookahead filter's greedy disturbance corners")
        xg, ug = x[greedy:], u[greedy:]
        corners = torch.cartesian_prod(
            *[torch.tensor([lo, hi], dtype=d.dtype, device=d.device) for lo, hi in zip(box.low, box.high)]
        ).reshape(-1, system.disturbance_dim)
        c = 1 + len(corners)  # candidates: d (its step is y's), then each corner, (c, G) flattened
        at_corners = self.step_ahead(
            xg.repeat(len(corners), 1), ug.repeat(len(corners), 1), corners.repeat_interleave(xg.shape[0], 0)
        )
        ahead = torch.cat([y[greedy:], at_corners])
        inside = self._inside(ahead, domain)
        clamped = torch.where(inside.unsqueeze(-1), ahead, ahead.clamp(domain[:, 0], domain[:, 1]))
        if isinstance(t, torch.Tensor) and t.ndim:
            t = t[greedy:].repeat(c)
        v = self.value_function.value(clamped, t)
        self._trust(clamped, t, v, None, None)
        worst = self._safety_value(v, ahead, inside).reshape(c, -1).argmin(0)
        chosen = ahead.reshape(c, -1, x.shape[-1])[worst, torch.arange(xg.shape[0], device=x.device)]
        return torch.cat([y[:greedy], chosen])

    def _safety_value(self, v: torch.Tensor, y: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
        """How far predicted states lie on the good side, ``> threshold`` to pass.

        Avoid: ``min(V, l)``, ``l`` alone outside the domain (no trusted ``V`` there). ``V <= l`` holds
        for the exact value function; a network or a grid's interpolation can break it at the
        failure set's edge. Reach kinds: ``min(-V, g)`` (``-V`` for reach; ``-V <= g`` likewise holds
        for the exact value), ``+inf`` where the target is reached (the task is done), ``-inf``
        outside the domain (nothing certifies reaching from there)."""
        if not self.problem.reaches:
            margin = self.system.failure_margin(y).to(v.dtype)
            return torch.where(inside, torch.minimum(v, margin), margin)
        oriented = self.problem.orient(v)
        if self.problem.has_constraint:
            oriented = torch.minimum(oriented, self.system.constraint_margin(y).to(v.dtype))
        oriented = torch.where(inside, oriented, -math.inf)
        return torch.where(self._reached(y), math.inf, oriented)

    def _reached(self, y: torch.Tensor) -> torch.Tensor:
        """Where a reach kind's target is reached (``l < 0``, and ``g > 0`` for reach-avoid: the
        boundary value ``max(l, -g) < 0``); never for avoid."""
        if not self.problem.reaches:
            return torch.zeros(y.shape[:-1], dtype=torch.bool, device=y.device)
        g = self.system.constraint_margin(y) if self.problem.has_constraint else None
        return self.problem.boundary_value(self.system.target_margin(y), g) < 0

    def _finished(self, y: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """Where a backup path stops for good: reach kinds at the target or out of time-to-go."""
        done = self._reached(y)
        if self.problem.reaches:
            done = done | (torch.as_tensor(t, device=y.device) <= 0)
        return done

    def _after(self, t: float | torch.Tensor, steps: int) -> float | torch.Tensor:
        """The time-to-go ``steps`` filter steps after ``t``: counted down for reach kinds (floored
        at 0; the task's deadline approaches), held for avoid (the fixed-horizon tube)."""
        if not self.problem.reaches or steps == 0 or self.dt is None:
            return t
        if isinstance(t, torch.Tensor):
            return (t - steps * self.dt).clamp_min(0.0)
        return max(float(t) - steps * self.dt, 0.0)
