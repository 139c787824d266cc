"""Safety filters around a value function: keep the nominal input unless the value says danger.

``SafetyFilter(vf, threshold, kind=...)(x, t, u_nominal) -> (u, info)``, batched over states; the
options are one :class:`~safety.filters.settings.FilterSettings`, given whole
(``SafetyFilter(vf, settings=FilterSettings(kind="smooth"))``) or field by field as keywords.
:class:`SafetyFilter` is the one entry point and the base every kind shares: it returns the class of
the kind asked for, each in its own module with its own decision rule (every env adapter in
:mod:`safety.filters.wrappers` takes each):

- ``"switch"`` (:class:`~safety.filters.switch.SwitchFilter`, least-restrictive): keep the nominal
  input where the value at the current state is above the threshold, else apply the backup input.
  The cheapest rule; it reacts one decision late, which its default threshold covers.
- ``"lookahead"`` (:class:`~safety.filters.lookahead.LookaheadFilter`, a backup shield): keep the
  nominal input only where the state one step ahead, and a rollout of the backup policy from there,
  stay safe. It checks what the next step does instead of where the state is, so its default
  threshold is 0.
- ``"smooth"`` (:class:`~safety.filters.smooth.SmoothFilter`, a control barrier-value function):
  the input closest to the nominal one that meets the HJ barrier condition, so the input changes
  gradually instead of jumping to the backup input at a boundary. Avoid problems only.

Measured (collisions, chattering, cost per decision of each kind): docs/results/filters.md.

What every kind shares lives here: the settings in force, the checks of the states, times and nominal
inputs (:meth:`SafetyFilter.__call__`), one evaluation of ``V``, ``grad V``, ``u*`` and ``d*`` per
decision, refused where any is not finite, the backup input, and the states outside the domain.

The backup input (``policy``): ``"gradient"`` is ``u*``; ``"greedy"`` is
:class:`~safety.value_policies.GreedyPolicy`'s input, the candidate input held for a short step that
leaves the most value. It replaces ``u*`` wherever a filter applies or rolls out its backup input
(the switch's intervention, the lookahead's backup rollout and fallback, the smooth filter's
infeasible steps), and only the rows that need it pay for it. Where ``grad V`` blends two manoeuvres
(three cars converging, each able to turn either way), ``u*`` can steer into both; the greedy input
commits to one. Each kind's default (:data:`~safety.filters.settings.DEFAULT_POLICIES`) and why it
is that kind's is in the kind's module.

The time-to-go ``t`` is the caller's choice (see :mod:`safety.filters.wrappers`). Every kind fails
closed: a non-finite value, gradient or optimal input raises instead of passing the nominal input,
and a state outside the system's domain keeps no nominal input (the backup input is applied).

Reach kinds (``system.kind`` ``"reach"`` or ``"reach-avoid"``, :mod:`reach.systems.problem`): the
filter keeps a task *feasible* instead of a system safe. ``{V(x, t) <= 0}`` is where the target can
be reached within the time-to-go ``t`` (reach-avoid: while the constraint margin ``g`` stays
positive), the control minimises ``V`` and the disturbance maximises it, so ``u*`` (the gradient's,
:meth:`~reach.systems.base.ControlAffineSystem.optimal_control`) is the minimising input. Every
decision reads ``V`` through :meth:`~reach.systems.problem.ProblemKind.orient` (``V`` for avoid,
``-V`` for reach kinds: ``> 0`` is the good side for both), so one implementation of each kind serves
both; each kind's module says what that means for it. The backup input is ``u*``
(``policy="gradient"``; ``"greedy"`` is refused: :func:`~safety.filters.settings.settings_for_system`).
The time-to-go counts down: the caller passes ``t = horizon - elapsed`` each step (the env adapters
do), and where it has run out nothing can be certified and ``u*`` is applied. ``FilterInfo`` keeps
its fields: ``value`` is ``V`` itself (not oriented), ``intervened`` the override. A value function
of another kind than the system the filter serves (``system=``) is refused at construction, naming
both kinds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import torch

from reach.systems.base import ControlAffineSystem
from reach.systems.box import project_inputs
from reach.validation import positive_finite
from reach.value_function import ValueFunction
from safety.filters.settings import (
    REMAINING,
    FilterSettings,
    make_filter_settings,
    settings_for_system,
)
from safety.tracing import only_rows, refuse_untrusted, tracing
from safety.value_policies import GreedyPolicy, OptimalPolicy, check_states

__all__ = ["Evaluation", "FilterInfo", "SafetyFilter", "require_served_kind"]

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


class Evaluation(NamedTuple):
    """What one decision reads of the value function at its states: ``V``, ``grad V``, ``u*`` and
    ``d*`` (None for a system without a disturbance), all finite (:meth:`SafetyFilter._evaluate`)."""

    value: torch.Tensor
    gradient: torch.Tensor
    u_star: torch.Tensor
    d_star: torch.Tensor | None


def _asked_kind(options: dict[str, Any]) -> object:
    """The kind a constructor call asks for: ``kind=``, else its ``settings``' kind, else the default."""
    kind = options.get("kind")
    if kind is None:
        settings = options.get("settings")
        kind = settings.kind if isinstance(settings, FilterSettings) else FilterSettings.kind
    return kind


class SafetyFilter:
    """A safety filter around a value function (see the module docstring); calling the class makes
    the filter of the kind asked for (:class:`~safety.filters.switch.SwitchFilter`,
    :class:`~safety.filters.lookahead.LookaheadFilter`, :class:`~safety.filters.smooth.SmoothFilter`,
    each a :class:`SafetyFilter`).

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
    settings in force. A kind's own class may be called as well, without ``kind=``; asked for
    another kind, it refuses, naming both.
    """

    #: the kind a subclass decides (its class statement's ``kind=``); None on the base itself
    KIND: ClassVar[str | None] = None
    #: the class of each kind, filled as each kind's module is loaded (:mod:`safety.filters` loads all)
    _KIND_CLASSES: ClassVar[dict[str, type[SafetyFilter]]] = {}

    def __init_subclass__(cls, kind: str | None = None, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if kind is not None:
            cls.KIND = kind
            SafetyFilter._KIND_CLASSES[kind] = cls

    def __new__(cls, *args: Any, **kwargs: Any) -> SafetyFilter:
        if cls is SafetyFilter:  # the public entry point: the class of the kind asked for
            kind = _asked_kind(kwargs)
            cls = SafetyFilter._KIND_CLASSES.get(kind, cls) if isinstance(kind, str) else cls
        return super().__new__(cls)

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
        if self.KIND is not None and options.get("kind") is None:
            options["kind"] = self.KIND  # a kind's own class needs no kind=
        settings = settings_for_system(
            make_filter_settings(settings, threshold=threshold, **options), value_function.system
        )
        if settings.kind != self.KIND:
            raise ValueError(
                f"{type(self).__name__} decides the {self.KIND!r} kind, not {settings.kind!r}; "
                f"SafetyFilter(..., kind={settings.kind!r}) makes a filter of that kind"
            )
        self._check_inputs(value_function.system)  # refused now, before any decision, not at the first one
        if dt is not None:
            dt = positive_finite("the filter's step dt", dt)
        horizon = value_function.system.horizon if settings.backup_horizon is None else settings.backup_horizon
        self.backup_steps = self._backup_steps(value_function.system, dt, integrator, horizon)
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
        self.kind = settings.kind
        self.dt = dt
        self.gamma = float(settings.gamma)
        self.outside_domain = settings.outside_domain
        self._settings = make_filter_settings(settings, threshold=self.threshold)  # the rule resolved

    def _check_inputs(self, system: ControlAffineSystem) -> None:
        """Refuse a control set this kind cannot decide over (every one, unless a kind says otherwise)."""

    def _backup_steps(self, system: ControlAffineSystem, dt: float | None, integrator: str, horizon: float) -> int:
        """How many held steps of the backup policy a decision rolls out after the nominal step
        (0 unless a kind predicts), set up once for ``dt`` (checked) and ``integrator``."""
        return 0

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
        seen = self._evaluate(x, t)
        u_nominal = given.to(seen.u_star.dtype)
        inside = self._inside(system.wrap(x), system.domain_tensor(x.dtype, x.device))
        trusted = inside | (self.outside_domain == "extrapolate")
        keep, applied, infeasible = self._choose(x, t, u_nominal, seen, trusted)
        # kept inputs come back as given (bit for bit, in their own dtype); the others in that dtype too
        applied = torch.where(keep.unsqueeze(-1), given, applied.to(given.dtype))
        # intervened = the filter overrode the nominal input (its decision; the applied input can
        # still equal the nominal one, e.g. where u* is the box centre and the nominal input is 0)
        return applied, FilterInfo(seen.value, given, applied, ~keep, infeasible, ~inside, seen.gradient)

    def _choose(
        self, x: torch.Tensor, t: float | torch.Tensor, u_nominal: torch.Tensor, seen: Evaluation, trusted: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The kind's decision rule: ``(keep, applied, infeasible)``, where ``keep`` (False wherever
        ``trusted`` is) marks the states that keep ``u_nominal`` (clipped into the control set, in
        ``u*``'s dtype), ``applied`` the input elsewhere and ``infeasible`` the smooth filter's flag
        (None for the other kinds)."""
        raise NotImplementedError(f"{type(self).__name__} has no decision rule; SafetyFilter(..., kind=...) makes one")

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

    # ------------------------------------------------------------------ what every kind reads
    def _evaluate(self, x: torch.Tensor, t: float | torch.Tensor) -> Evaluation:
        """``(V, grad V, u*, d*)`` from the policy, refused where untrusted (``d*`` None without a disturbance)."""
        value, p, u_star, d_star = self.policy.evaluate(x, t)
        self._trust(x, t, value, p, u_star)
        return Evaluation(value, p, u_star, d_star if self.system.disturbance_dim else None)

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

    # ------------------------------------------------------------------ fail closed
    def _trust(
        self,
        x: torch.Tensor,
        t: float | torch.Tensor,
        value: torch.Tensor,
        p: torch.Tensor | None,
        u_star: torch.Tensor | None,
    ) -> None:
        """Refuse (raise, or record while a graph is traced: :mod:`safety.tracing`) a non-finite
        value, gradient or optimal input, naming the first state it came from."""
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
