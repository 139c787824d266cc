"""Safety filters around a value function: keep the nominal input unless the value says danger.

``SafetyFilter(vf, threshold, kind=...)(x, t, u_nominal) -> (u, info)``, batched over states; the
options are one :class:`~safety.filters.settings.FilterSettings`, given whole
(``SafetyFilter(vf, settings=FilterSettings(kind="smooth"))``) or field by field as keywords. Three
kinds, one interface (every env adapter in :mod:`safety.filters.wrappers` takes each):

- ``"switch"`` (least-restrictive): keep ``u_nominal`` where ``V(x, t) > threshold``, else apply
  the backup input (by default the greedy input, see below; ``policy="gradient"``: ``u*``). Decides
  on the current state, so between two decisions of a zero-order-hold controller ``V`` can fall by
  about ``|dl/dt|_max dt``: its default threshold in the env adapters covers that.
- ``"lookahead"`` (a backup shield): predict the state one step ``dt`` ahead under ``u_nominal``
  (the system's own integrator, inputs held over the step), then roll the backup policy ``u*``
  forward from there for ``backup_horizon`` seconds (default: the system's horizon, the time the BRT
  speaks for), and keep ``u_nominal`` only if ``min(V, l)`` stays above ``threshold`` at every
  predicted state; else apply ``u*`` (or the control box's centre where ``u*`` fails the same check
  and the centre passes it: :meth:`SafetyFilter._fallback`). Checking one step of ``u*`` is not
  enough at threshold 0: near the BRT's edge a held ``u*`` loses a little value each step, and
  states ride the failure set's edge into a graze. ``backup_disturbance="robust"`` (default) checks
  two predicted paths: the value function's ``d*``, and a greedy worst case that each step takes
  whichever of ``d*`` and the disturbance box's corners leaves the least ``min(V, l)`` (the real
  disturbance need not be the model's ``d*``, e.g. a pursuer steered by another value function);
  ``"model"`` checks the first alone. On Air3D (101^3 grid truth, worst-case pursuer, 1,000 attacked
  episodes) it lets none collide at threshold 0; checking one step of ``u*`` let 3.3 % graze the
  failure set.
- ``"smooth"``: the input closest to ``u_nominal`` (least squares) that satisfies the HJ barrier
  condition ``grad V . f(x, u, d*) + gamma (V - threshold) >= 0`` inside the input box (control
  barrier-value functions, Choi et al. 2021). For control-affine systems the condition is one linear
  inequality in ``u``, so the problem is a projection onto a half-space within a box, solved exactly
  and batched (the multiplier is found between the kinks where inputs saturate; no QP solver).
  Where no input of the box satisfies it, ``u*`` (the input that does best) is applied and
  ``info.infeasible`` says so. The time-to-go is held fixed over the step (the fixed-horizon filter
  of the env adapters), so ``dV/dt`` drops out.

The backup input (``policy``): ``"gradient"`` is ``u*``; ``"greedy"`` is
:class:`~safety.value_policies.GreedyPolicy`'s input, the candidate input held for a short step that leaves
the most value. It replaces ``u*`` wherever a filter applies or rolls out its backup input (the
switch's intervention, the lookahead's backup rollout and fallback, the smooth filter's infeasible
steps). Where ``grad V`` blends two manoeuvres (three cars converging, each able to turn either
way), ``u*`` can steer into both; the greedy input commits to one. Defaults
(:data:`DEFAULT_POLICIES`): greedy for the switch, which pays for it only where it intervenes (the
shipped 9D model's switch lets 4.4 % of three-car merges collide with ``u*``, none with the greedy
input; docs/filters.md). Gradient for the lookahead, which verifies its backup rollout before it
relies on it, and whose every backup step would cost ``2^m_u + 1`` value evaluations instead of
one; and for the smooth filter, whose fallback is by definition the input that does best on its
barrier condition (``u*``).

The time-to-go ``t`` is the caller's choice (see :mod:`safety.filters.wrappers`). Every kind fails closed: a
non-finite value, gradient or optimal input raises instead of passing the nominal input.

Reach kinds (``system.kind`` ``"reach"`` or ``"reach-avoid"``, :mod:`reach.systems.problem`): the
filter keeps a task *feasible* instead of a system safe. ``{V(x, t) <= 0}`` is where the target can
be reached within the time-to-go ``t`` (reach-avoid: while the constraint margin ``g`` stays
positive), the control minimises ``V`` and the disturbance maximises it, so ``u*`` (the gradient's,
:meth:`~reach.systems.base.ControlAffineSystem.optimal_control`) is the minimising input. Every
decision reads ``V`` through :meth:`~reach.systems.problem.ProblemKind.orient` (``V`` for avoid,
``-V`` for reach kinds: ``> 0`` is the good side for both), so one implementation serves both:

- the switch keeps ``u_nominal`` where ``V(x, t) < -threshold``, else applies ``u*``;
- the lookahead keeps it where the state one step ahead under ``u_nominal`` has
  ``V(y, t - dt) < -threshold`` and the backup rollout of ``u*`` after it keeps
  ``min(-V, g) > threshold`` (``-V`` alone for reach) until it reaches the target (``l < 0`` and
  ``g > 0``: the task is done there, and the path stops) or its time-to-go runs out; else ``u*``
  (or the centre, as for avoid). A predicted state outside the domain certifies nothing (``-inf``);
- the smooth filter refuses reach kinds at construction: its barrier condition holds the time-to-go
  fixed so that ``dV/dt`` drops out, sound for avoid's fixed-horizon tube, but a reach task has a
  deadline: the countdown puts ``dV/dt`` into the condition (the value function gives no time
  derivative), and with ``t`` held fixed a car circling inside ``{V(., T) < 0}`` meets the
  condition while the deadline passes;
- the backup input is ``u*`` (``policy="gradient"``; ``"greedy"`` is refused:
  :func:`~safety.filters.settings.settings_for_system`).

The time-to-go counts down: the caller passes ``t = horizon - elapsed`` each step (the env adapters
do, :mod:`safety.filters.wrappers`), and the lookahead predicts at ``t - dt``, ``t - 2 dt``, ... (floored at
0). Where ``t`` has run out (``t <= 0`` for the switch, ``t < dt`` for the lookahead, whose nominal
step would end past the deadline) nothing can be certified and ``u*`` is applied. For avoid the
lookahead evaluates its predictions at ``t`` itself (the fixed horizon of the env adapters; avoid's
tube value only falls as ``t`` grows, so holding ``t`` is the cautious side), as before.
``FilterInfo`` keeps its fields: ``value`` is ``V`` itself (not oriented), ``intervened`` the
override. A value function of another kind than the system the filter serves (``system=``) is
refused at construction, naming both kinds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from reach.integrators import check_integrator, make_stepper
from reach.systems.arrays import TORCH
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Ball, InputSet, require_box
from reach.validation import positive_finite
from reach.value_function import ValueFunction
from safety.filters.settings import (
    DEFAULT_GAMMA,
    DEFAULT_POLICIES,
    KINDS,
    LOOKAHEAD_DISTURBANCES,
    MAX_BACKUP_STEPS,
    REMAINING,
    FilterSettings,
    make_filter_settings,
    resolve_policy,
    settings_for_system,
)
from safety.tracing import only_rows, refuse_untrusted, tracing
from safety.value_policies import GreedyPolicy, OptimalPolicy, check_states

__all__ = [
    "DEFAULT_GAMMA",
    "DEFAULT_POLICIES",
    "KINDS",
    "LOOKAHEAD_DISTURBANCES",
    "FilterInfo",
    "FilterSettings",
    "SafetyFilter",
    "make_filter_settings",
    "require_served_kind",
    "resolve_policy",
]

#: slack (s) on the lookahead's "a whole step of time-to-go is left" (times summed in float arithmetic)
TIME_SLACK = 1e-9


def require_served_kind(served: ControlAffineSystem, value_system: ControlAffineSystem) -> None:
    """Refuse a value function whose kind of problem differs from the system's the filter serves,
    naming both kinds: an avoid value's ``V > 0`` (safe) read for a reach task, or a reach value's
    ``V < 0`` (reachable) read for an avoid one, would keep the nominal input on the wrong side."""
    if served.kind != value_system.kind:
        raise ValueError(
            f"the value function solves a problem of kind {value_system.kind!r} ({value_system.name}), but the "
            f"filter serves one of kind {served.kind!r} ({served.name}); a filter needs a value function of its "
            "system's kind"
        )


@dataclass
class FilterInfo:
    """What the filter saw and did, per state: value, nominal and applied input, intervention.

    ``intervened`` is True where the filter overrode the nominal input (the switch and the lookahead
    judged it unsafe; the smooth filter found it violating the barrier condition; every kind where
    the state lies outside the value function's domain); ``infeasible`` (smooth filter) where no
    input of the box met the condition and ``u*`` was applied; ``outside_domain`` where the state
    lay outside the system's domain, where ``V`` is extrapolated and trusted for nothing; ``gradient``
    is ``grad V`` at the state.
    """

    value: torch.Tensor
    nominal: torch.Tensor
    applied: torch.Tensor
    intervened: torch.Tensor
    infeasible: torch.Tensor | None = None
    outside_domain: torch.Tensor | None = None
    gradient: torch.Tensor | None = None


def project_inputs(u: torch.Tensor, bounds: InputSet) -> torch.Tensor:
    """``u`` moved into the input set: clipped to a box, scaled back onto a ball along ``u - c``."""
    if isinstance(bounds, Ball):
        c = u.new_tensor(bounds.center)
        norm = torch.linalg.vector_norm(u - c, dim=-1, keepdim=True)
        return c + (u - c) * torch.clamp(bounds.radius / norm.clamp_min(1e-300), max=1.0)
    return torch.minimum(torch.maximum(u, u.new_tensor(bounds.low)), u.new_tensor(bounds.high))


class SafetyFilter:
    """A safety filter around a value function (see the module docstring).

    Args:
        value_function: any :class:`ValueFunction` (network, DeepReach import, grid solution).
        threshold: the level treated as the boundary (a small positive margin buys robustness);
            ``None`` or not given: ``settings.threshold``, whose ``None`` here means 0 (the default
            rule for a filter acting every env step is the adapters', :meth:`FilterSettings.threshold_for`).
        settings: the :class:`~safety.filters.settings.FilterSettings` (kind, gamma, backup horizon,
            backup disturbance, backup policy); default ``FilterSettings()``.
        dt: the step the lookahead predicts over (required for ``"lookahead"``; the env adapters
            pass the env's ``dt``).
        integrator: how the lookahead predicts (``"rk4"``, the envs' default, or ``"euler"``).
        system: the system the filter serves (the env adapters pass the env's): a value function of
            another kind of problem is refused naming both kinds, then one of other physics;
            ``None``: the value function's own system.
        **options: any :class:`FilterSettings` field by name (``kind="smooth", gamma=2.0``), a
            convenience that replaces that field of ``settings``
            (:func:`~safety.filters.settings.make_filter_settings`).

    ``policy="greedy"`` backs up with :class:`~safety.value_policies.GreedyPolicy`, predicted with
    ``integrator`` in steps of ``dt``. ``settings`` (the threshold as now set) reads back the
    settings in force.
    """

    def __init__(
        self,
        value_function: ValueFunction,
        threshold: float | None = None,
        *,
        settings: FilterSettings | None = None,
        dt: float | None = None,
        integrator: str = "rk4",
        system: ControlAffineSystem | None = None,
        **options: Any,
    ) -> None:
        if system is not None:
            require_served_kind(system, value_function.system)
            system.require_same_physics(value_function.system, "the filter's value function")
        settings = settings_for_system(
            make_filter_settings(settings, threshold=threshold, **options), value_function.system
        )
        kind = settings.kind
        if kind == "smooth":  # refused now, before any decision, not at the first one
            require_box(value_function.system.control_bounds, "the smooth filter (its projection is over a box)")
        if dt is not None:
            dt = positive_finite("the filter's step dt", dt)
        if kind == "lookahead":
            if dt is None:
                raise ValueError("the lookahead filter needs a step dt > 0, got None")
            self._stepper = make_stepper(value_function.system, dt, check_integrator(integrator), TORCH)
        horizon = value_function.system.horizon if settings.backup_horizon is None else settings.backup_horizon
        # steps of the backup rollout (the lookahead only): enough held steps to cover the horizon
        self.backup_steps = math.ceil(horizon / dt - 1e-9) if kind == "lookahead" else 0
        if self.backup_steps > MAX_BACKUP_STEPS:
            raise ValueError(
                f"backup_horizon {horizon:g} s at dt {dt:g} s is {self.backup_steps} backup steps per decision; "
                f"at most {MAX_BACKUP_STEPS} (lower backup_horizon or raise dt)"
            )
        self.backup_horizon = float(horizon)
        self.backup_disturbance = settings.backup_disturbance
        self.value_function = value_function
        self.system = value_function.system
        self.problem = self.system.problem
        self.policy = OptimalPolicy(value_function)
        self.policy_name = settings.backup_policy
        self.greedy = (
            GreedyPolicy(value_function, **({} if dt is None else {"dt": float(dt)}), integrator=integrator)
            if self.policy_name == "greedy"
            else None
        )
        self.threshold = settings.threshold_for(self.system)
        self.kind = kind
        self.dt = dt
        self.gamma = float(settings.gamma)
        self.outside_domain = settings.outside_domain
        self._settings = make_filter_settings(settings, threshold=self.threshold)  # the rule resolved

    @property
    def settings(self) -> FilterSettings:
        """The :class:`FilterSettings` in force, with the threshold as now set (it may change between calls)."""
        if self._settings.threshold == self.threshold:
            return self._settings
        return make_filter_settings(self._settings, threshold=self.threshold)

    def __call__(
        self, x: torch.Tensor, t: float | torch.Tensor, u_nominal: torch.Tensor
    ) -> tuple[torch.Tensor, FilterInfo]:
        """Filtered inputs ``(..., m_u)`` for states ``(..., n)`` and nominal inputs ``(..., m_u)``.

        Nominal inputs are physical units, in any floating dtype. One outside the control box is
        clipped to it first (it cannot be applied, so it is neither judged nor kept as given;
        ``FilterInfo.nominal`` holds the clipped input); where kept, inputs come back bit for bit in
        their own dtype. NaN/inf in states or nominal inputs, integer or meta-device tensors, a
        time-to-go that is not a number (or one per state), one the value function does not cover,
        and a non-finite value, gradient or ``u*`` raise ``ValueError``: no kind passes the nominal
        input on a value it cannot trust.
        """
        system = self.system
        check_states(x, system.state_dim)
        self._check_time(t, x.shape[:-1])
        if not isinstance(u_nominal, torch.Tensor) or u_nominal.shape != (*x.shape[:-1], system.control_dim):
            shape = tuple(u_nominal.shape) if isinstance(u_nominal, torch.Tensor) else type(u_nominal).__name__
            raise ValueError(f"u_nominal must have shape {(*x.shape[:-1], system.control_dim)}, got {shape}")
        if not u_nominal.dtype.is_floating_point:
            raise ValueError(f"u_nominal must be a floating-point tensor, got {u_nominal.dtype}")
        if not bool(torch.isfinite(u_nominal).all()):
            raise ValueError(f"u_nominal contains NaN or inf: {u_nominal[~torch.isfinite(u_nominal)][:4].tolist()}")
        return self.decide(x, t, u_nominal)

    def decide(
        self, x: torch.Tensor, t: float | torch.Tensor, u_nominal: torch.Tensor
    ) -> tuple[torch.Tensor, FilterInfo]:
        """The decision itself, on inputs :meth:`__call__` has checked (the exported graph traces
        this method: :mod:`safety.filters.export`, :mod:`safety.tracing`).

        A state outside the system's domain (headings wrapped first) keeps no nominal input, in every
        kind: a network there extrapolates beyond the states it was trained on, and its ``V`` is
        trusted for nothing; the backup input is applied (``info.outside_domain`` says where;
        ``FilterSettings(outside_domain="extrapolate")`` decides there as inside).
        """
        system = self.system
        # an input outside the control set cannot be applied: every kind decides on (and keeps) the
        # input the system would get, the nominal one clipped to the box or scaled into the ball
        # (unchanged where inside)
        given = project_inputs(u_nominal, system.control_bounds)
        value, p, u_star, d_star = self._evaluate(x, t)
        u_nominal = given.to(u_star.dtype)
        inside = self._inside(system.wrap(x), system.domain_tensor(x.dtype, x.device))
        trusted = inside | (self.outside_domain == "extrapolate")
        infeasible = None
        if self.kind == "switch":
            # a NaN value compares False with everything: "not above" (never "at or below") decides;
            # oriented, "> threshold" is the good side of every kind (V > thr avoid, V < -thr reach)
            keep = (self.problem.orient(value) > self.threshold) & self._time_left(t, 0.0, value) & trusted
            applied = torch.where(keep.unsqueeze(-1), u_nominal, self._backup_input(x, t, u_star, d_star, ~keep))
        elif self.kind == "lookahead" and tracing():
            keep, applied = self._lookahead_every_row(x, t, u_nominal, u_star, d_star, trusted)
        elif self.kind == "lookahead":
            keep = self._backup_holds(x, t, u_nominal, d_star) & trusted
            u_back = self._backup_input(x, t, u_star, d_star, ~keep)
            applied = torch.where(keep.unsqueeze(-1), u_nominal, self._fallback(x, t, u_back, d_star, ~keep))
        else:
            applied, infeasible, keep = self._project(x, value, p, u_nominal, u_star, d_star)
            infeasible = infeasible & trusted
            keep = keep & trusted
            backup = ~trusted | infeasible
            applied = torch.where(backup.unsqueeze(-1), self._backup_input(x, t, u_star, d_star, backup), applied)
        # kept inputs come back as given (bit for bit, in their own dtype); the others in that dtype too
        applied = torch.where(keep.unsqueeze(-1), given, applied.to(given.dtype))
        # intervened = the filter overrode the nominal input (its decision; the applied input can
        # still equal the nominal one, e.g. where u* is the box centre and the nominal input is 0)
        return applied, FilterInfo(value, given, applied, ~keep, infeasible, ~inside, p)

    def _check_time(self, t: object, batch: torch.Size) -> None:
        """Refuse a time-to-go that is not a number or a tensor of one per state, naming it."""
        if isinstance(t, str):
            hint = " (a wrapper option: time_to_go='remaining')" if t == REMAINING else ""
            raise ValueError(f"t must be a time-to-go in seconds or a tensor of them, got {t!r}{hint}")
        if isinstance(t, torch.Tensor) and t.ndim:
            if t.shape != batch and t.numel() != 1:
                raise ValueError(f"a per-state t must have shape {tuple(batch)} (one per state), got {tuple(t.shape)}")
            if not t.dtype.is_floating_point or t.is_meta:
                raise ValueError(f"t must be a floating-point tensor of times-to-go, got {t.dtype}")

    # ------------------------------------------------------------------ the kinds
    def _evaluate(
        self, x: torch.Tensor, t: float | torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(V, grad V, u*, d*)`` from the policy, refused where untrusted (``d*`` None without a disturbance)."""
        value, p, u_star, d_star = self.policy.evaluate(x, t)
        self._trust(x, t, value, p, u_star)
        return value, p, u_star, d_star if self.system.disturbance_dim else None

    def _backup_input(
        self,
        x: torch.Tensor,
        t: float | torch.Tensor,
        u_star: torch.Tensor,
        d_star: torch.Tensor | None,
        rows: torch.Tensor,
    ) -> torch.Tensor:
        """The backup input: ``u_star``, with the greedy policy's input on ``rows`` (a mask of the
        batch) when ``policy="greedy"``; only those rows pay for it."""
        if self.greedy is None:
            return u_star
        if tracing():  # a graph computes every row (no value-dependent indexing); its checks count on rows
            with only_rows(rows):
                greedy = self.greedy.control(x, t, d_star).to(u_star.dtype)
            return torch.where(rows.unsqueeze(-1), greedy, u_star)
        if not bool(rows.any()):
            return u_star
        index = torch.nonzero(rows.reshape(-1)).squeeze(-1)
        xs, ts, ds = self._rows(index, x, t, d_star)
        out = u_star.clone().reshape(-1, self.system.control_dim)
        out[index] = self.greedy.control(xs, ts, ds).to(out.dtype)
        return out.reshape(u_star.shape)

    def _rows(
        self, index: torch.Tensor, x: torch.Tensor, t: float | torch.Tensor, d: torch.Tensor | None
    ) -> tuple[torch.Tensor, float | torch.Tensor, torch.Tensor | None]:
        """States, times-to-go and disturbances of the flattened batch at ``index`` (a scalar time
        stays as it is; per-state times follow their states)."""
        flat = x.reshape(-1, self.system.state_dim)
        ts = t.reshape(-1).expand(flat.shape[0])[index] if isinstance(t, torch.Tensor) and t.ndim else t
        return flat[index], ts, None if d is None else d.reshape(-1, d.shape[-1])[index]

    def _ahead(self, x: torch.Tensor, u: torch.Tensor, d: torch.Tensor | None) -> torch.Tensor:
        """The state one step ``dt`` ahead under ``u`` and ``d`` held over the step."""
        system = self.system
        cols = TORCH.unbind(x)
        uc = system.input_columns(u, system.control_bounds, "u")
        dc = system.input_columns(d, system.disturbance_bounds, "d")
        return TORCH.stack(self._stepper(cols, uc, dc), like=cols[0])

    def _backup_holds(
        self, x: torch.Tensor, t: float | torch.Tensor, u_nominal: torch.Tensor, d_star: torch.Tensor | None
    ) -> torch.Tensor:
        """Where ``min(V, l)`` stays above the threshold over the nominal step and the backup rollout
        after it, along every predicted disturbance path (the lookahead's decision). Reach kinds:
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
        u_start = u_nominal.reshape(-1, system.control_dim).repeat(paths, 1)
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
        between box corners from step to step, losing a little ``l`` with every held corner (the one
        collision of the 10-minute Air3D network at threshold 0, docs/filters.md); the centre is the
        candidate that does not chatter. Only the states that need a fallback are checked again.
        """
        fallback = u_star.clone()
        m = self.system.control_dim
        centre = torch.tensor(self.system.control_bounds.center, dtype=u_star.dtype, device=u_star.device)
        if not bool(needed.any()):
            return fallback
        rows = torch.nonzero(needed.reshape(-1)).squeeze(-1)
        xs, ts, ds = self._rows(rows, x, t, d_star)
        us = u_star.reshape(-1, m)[rows]
        failing = ~self._backup_holds(xs, ts, us, ds)
        if not bool(failing.any()):
            return fallback
        rows, xs, us = rows[failing], xs[failing], us[failing]  # only where u* fails is the centre checked
        ts = ts[failing] if isinstance(ts, torch.Tensor) and ts.ndim else ts
        ds = None if ds is None else ds[failing]
        centre = centre.expand_as(us)
        use_centre = self._backup_holds(xs, ts, centre, ds)
        flat = fallback.reshape(-1, m)
        flat[rows[use_centre]] = centre[use_centre]
        return flat.reshape(u_star.shape)

    def _lookahead_every_row(
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
        holds = self._backup_holds(flat_x.repeat(3, 1), tt, candidates, dd).reshape(3, *x.shape[:-1])
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
        y = self._ahead(x, u, d)
        if d is None or greedy is None:
            return y
        system = self.system
        box = require_box(system.disturbance_bounds, "the lookahead filter's greedy disturbance corners")
        xg, ug = x[greedy:], u[greedy:]
        corners = torch.cartesian_prod(
            *[torch.tensor([lo, hi], dtype=d.dtype, device=d.device) for lo, hi in zip(box.low, box.high)]
        ).reshape(-1, system.disturbance_dim)
        c = 1 + len(corners)  # candidates: d (its step is y's), then each corner, (c, G) flattened
        at_corners = self._ahead(
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

    def _time_left(self, t: float | torch.Tensor, need: float, like: torch.Tensor) -> torch.Tensor:
        """Where a reach kind's time-to-go exceeds ``need`` (0 for the switch, ``dt`` for the
        lookahead's nominal step, to :data:`TIME_SLACK`): elsewhere nothing can be certified and the
        filter fails closed. All True for avoid (``like``'s shape)."""
        ok = torch.ones(like.shape, dtype=torch.bool, device=like.device)
        if not self.problem.reaches:
            return ok
        tt = torch.as_tensor(t, dtype=torch.float64, device=like.device)
        left = tt > 0 if need == 0 else tt >= need - TIME_SLACK
        return ok & (left.reshape(()) if left.numel() == 1 else left.reshape(ok.shape))

    @staticmethod
    def _inside(y: torch.Tensor, domain: torch.Tensor) -> torch.Tensor:
        """Which states lie in the system's domain (wrapped headings always do)."""
        return ((y >= domain[:, 0]) & (y <= domain[:, 1])).all(-1)

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

    # ------------------------------------------------------------------ fail closed
    def _trust(
        self,
        x: torch.Tensor,
        t: float | torch.Tensor,
        value: torch.Tensor,
        p: torch.Tensor | None,
        u_star: torch.Tensor | None,
    ) -> None:
        untrusted = ~torch.isfinite(value)
        for tensor in (p, u_star):
            if tensor is not None:
                untrusted = untrusted | ~torch.isfinite(tensor).all(-1)
        refuse_untrusted(
            untrusted,
            lambda: (
                f"value function returned a non-finite value, gradient or optimal input at state "
                f"{x[untrusted][0].tolist()} (t = {t}); the filter does not trust it and keeps no nominal input"
            ),
        )
