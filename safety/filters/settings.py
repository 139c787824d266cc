"""One frozen group of filter options, validated once, passed whole from the CLI to the filter.

Which safety filter runs, and how, is a handful of options that always travel together: the kind,
the threshold, the time-to-go the env adapters evaluate ``V`` at, the smooth filter's barrier rate,
the lookahead's backup horizon and disturbance paths, and the backup input. :class:`FilterSettings`
holds them, checks them when it is made, and is the one source of their defaults, so a new option
is one new field, not an edit in every layer it passes through.

:func:`make_filter_settings` is the one place keyword options become settings:
``SafetyFilter(vf, threshold=0.1, kind="lookahead")``, ``SafetyFilterWrapper(env, vf, kind=...)``
and ``FilterConfig(label, vf, 0.2, kind=...)`` all go through it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from reach.validation import check_float
from safety.value_policies import check_policy

#: the filter kinds :class:`~safety.filters.base.SafetyFilter` offers
KINDS = ("switch", "lookahead", "smooth")

#: the disturbance paths the lookahead can check (see :mod:`safety.filters.lookahead`)
LOOKAHEAD_DISTURBANCES = ("robust", "model")

#: the backup input each kind uses unless told otherwise (see :mod:`safety.filters.base` and each kind's module)
DEFAULT_POLICIES = {"switch": "greedy", "lookahead": "gradient", "smooth": "gradient"}

#: what a filter does at a state outside the value function's domain (see :class:`FilterSettings`)
OUTSIDE_DOMAIN = ("backup", "extrapolate")

#: the time-to-go that counts down with the episode (``horizon - elapsed``, floored at 0)
REMAINING = "remaining"


#: the most held steps a lookahead's backup rollout may take per decision (``backup_horizon / dt``):
#: each is a batched value-and-gradient evaluation, so 1e6 s at dt 0.05 would never return
MAX_BACKUP_STEPS = 10_000


@dataclass(frozen=True)
class FilterSettings:
    """Which filter to run and how (see :mod:`safety.filters.base` and :mod:`safety.filters.wrappers`).

    Attributes:
        kind: ``"switch"``, ``"lookahead"`` or ``"smooth"``.
        threshold: the level treated as the boundary (finite, >= 0: below 0 the filter would keep
            the nominal input inside the unsafe set); ``None``: the default rule
            (:meth:`threshold_for`: ``2 * rate * dt`` for a switch or smooth filter acting every
            ``dt``, 0 for the lookahead or where no control period is known).
        time_to_go: where the env adapters evaluate ``V``: ``None`` at the system's horizon (avoid;
            for reach kinds ``None`` means ``"remaining"``: the task's deadline counts down), a
            number >= 0 (avoid only), or ``"remaining"`` (the time left in the episode). A bare
            :class:`~safety.filters.base.SafetyFilter` is given ``t`` by its caller and ignores it.
        gamma: the smooth filter's barrier rate (1/s, finite, >= 0; 0 forbids any decrease of ``V``).
        backup_horizon: how long (s) the lookahead rolls the backup policy after the nominal step
            (finite, >= 0; ``None``: the system's horizon; 0: the nominal step alone); at most
            :data:`MAX_BACKUP_STEPS` steps of the filter's ``dt``.
        backup_disturbance: the lookahead's predicted disturbance paths, ``"robust"`` or ``"model"``.
        policy: the backup input, ``"gradient"`` or ``"greedy"``; ``None``: the kind's default
            (:data:`DEFAULT_POLICIES`, :attr:`backup_policy`; always ``"gradient"`` for reach kinds,
            :func:`settings_for_system`).
        outside_domain: at a state outside the system's domain (headings wrapped first), where a
            network extrapolates beyond what it was trained on: ``"backup"`` (default, fail closed)
            keeps no nominal input and applies the backup input; ``"extrapolate"`` decides on the
            extrapolated ``V`` as inside (reach before 0.3 did this: a scene without an arena, where
            the Air3D evader escapes beyond the 1 m box, then keeps its nominal input).
    """

    kind: str = "switch"
    threshold: float | None = None
    time_to_go: float | str | None = None
    gamma: float = 5.0
    backup_horizon: float | None = None
    backup_disturbance: str = "robust"
    policy: str | None = None
    outside_domain: str = "backup"

    def __post_init__(self) -> None:
        """Refuse a setting that makes no sense, naming it and its value (the one check of each).
        Numbers may arrive as Python, NumPy or 0-d tensor reals; they are kept as Python floats."""
        if self.kind not in KINDS:
            raise ValueError(f"filter kind must be one of {KINDS}, got {self.kind!r}")
        if self.threshold is not None:  # below 0 the filter would keep u_nom inside the unsafe set
            self._set("threshold", check_float("threshold", self.threshold, 0))
        ttg = self.time_to_go
        if ttg is not None and ttg != REMAINING:
            if isinstance(ttg, str):
                raise ValueError(f"time_to_go must be None, {REMAINING!r} or a number >= 0, got {ttg!r}")
            self._set("time_to_go", check_float("time_to_go", ttg, 0))
        self._set("gamma", check_float("gamma", self.gamma, 0))
        if self.backup_horizon is not None:
            self._set("backup_horizon", check_float("backup_horizon (seconds)", self.backup_horizon, 0))
        if self.backup_disturbance not in LOOKAHEAD_DISTURBANCES:
            raise ValueError(
                f"backup_disturbance must be one of {LOOKAHEAD_DISTURBANCES}, got {self.backup_disturbance!r}"
            )
        if self.policy is not None:
            check_policy(self.policy)
        if self.outside_domain not in OUTSIDE_DOMAIN:
            raise ValueError(f"outside_domain must be one of {OUTSIDE_DOMAIN}, got {self.outside_domain!r}")

    def _set(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)  # a frozen dataclass stores its checked value once

    @property
    def backup_policy(self) -> str:
        """The backup input in force: :attr:`policy`, or the kind's default when it is None."""
        return resolve_policy(self.kind, self.policy)

    def threshold_for(self, system: Any, dt: float | None = None) -> float:
        """The threshold to filter at: :attr:`threshold`, else the default rule for a filter that
        acts every ``dt`` seconds (:func:`default_threshold`), else 0 (no control period given: a
        bare :class:`~safety.filters.base.SafetyFilter` takes the boundary itself)."""
        if self.threshold is not None:
            return float(self.threshold)
        return 0.0 if dt is None else default_threshold(system, dt, self.kind)

    def keywords(self) -> dict[str, Any]:
        """Every field by name (what Gymnasium records of a wrapper, and what rebuilds these settings)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


#: every option :class:`FilterSettings` holds, in field order
FIELDS = tuple(f.name for f in dataclasses.fields(FilterSettings))

#: the smooth filter's default barrier rate (1/s), read from :class:`FilterSettings`
DEFAULT_GAMMA: float = FilterSettings.gamma


def make_filter_settings(settings: FilterSettings | None = None, /, **options: Any) -> FilterSettings:
    """The one place keyword options become :class:`FilterSettings`.

    Without ``settings``: ``FilterSettings(**options)``. With ``settings``: those settings, the
    given options replacing their fields; an option of ``None`` counts as not given there (``None``
    is the default of every optional field), so an adapter's ``threshold=None`` leaves the settings'
    own threshold. Unknown option names raise ``TypeError`` naming them; bad values ``ValueError``.
    """
    unknown = sorted(set(options) - set(FIELDS))
    if unknown:
        raise TypeError(f"unknown filter option(s) {', '.join(map(repr, unknown))}; FilterSettings has {FIELDS}")
    if settings is None:
        return FilterSettings(**options)
    if not isinstance(settings, FilterSettings):
        raise TypeError(f"settings must be a FilterSettings, got {type(settings).__name__}")
    given = {name: value for name, value in options.items() if value is not None}
    return dataclasses.replace(settings, **given) if given else settings


def resolve_policy(kind: str, policy: str | None) -> str:
    """The backup input a filter of ``kind`` uses: ``policy``, or the kind's default when None."""
    return DEFAULT_POLICIES[kind] if policy is None else check_policy(policy)


def settings_for_system(settings: FilterSettings, system: Any) -> FilterSettings:
    """``settings`` as they apply to ``system``'s kind of problem (:attr:`system.problem`), refusing
    what that kind cannot use, naming it. Avoid problems take every setting as it is.

    Reach kinds (``"reach"``, ``"reach-avoid"``: the control minimises ``V``, see
    :mod:`safety.filters.base`) back up with the gradient's ``u*``: ``policy=None`` resolves to
    ``"gradient"``, and ``"greedy"`` is refused (:class:`~safety.value_policies.GreedyPolicy` maximises
    ``min(V, l)``, the avoid rule). They refuse the smooth kind (its barrier condition holds the
    time-to-go fixed, which would certify loitering past the deadline: :mod:`safety.filters.smooth`) and a
    fixed ``time_to_go`` (the task has a deadline: the time-to-go must count down with the episode).
    """
    problem = system.problem
    if not problem.reaches:
        return settings
    what = f"{system.name} is a {problem.name} problem"
    if settings.kind == "smooth":
        raise ValueError(
            f"the smooth filter serves avoid problems only; {what}: its barrier condition holds the "
            "time-to-go fixed (dV/dt drops out), which for a task with a deadline would certify "
            "loitering past it; use kind='switch' or 'lookahead'"
        )
    if settings.policy == "greedy":
        raise ValueError(
            f"policy='greedy' backs up with the input that maximises min(V, l), the avoid rule; {what} "
            "(the control minimises V): use policy='gradient' (u*)"
        )
    if settings.time_to_go is not None and settings.time_to_go != REMAINING:
        raise ValueError(
            f"time_to_go={settings.time_to_go!r} holds the time-to-go fixed; {what} with a deadline, so "
            f"the time-to-go must count down: use time_to_go=None or {REMAINING!r}"
        )
    return settings if settings.policy == "gradient" else dataclasses.replace(settings, policy="gradient")


def default_threshold(system: Any, dt: float, kind: str = "switch") -> float:
    """The default threshold of a filter kind in an env stepping ``dt``: the switch and the smooth
    filter decide on the current state, so theirs is ``2 * rate * dt``, twice what ``V`` can lose in
    one held step, with ``rate`` the system's :meth:`margin_rate_bound` or, for a system that declares
    none, :meth:`margin_rate_estimate` (sampled over the domain); the lookahead checks the next
    state, so 0. (For a reach kind the estimate samples the rate of ``V``'s boundary value, the target
    margin, or ``max(l, -g)`` for reach-avoid.)"""
    if kind == "lookahead":
        return 0.0
    bound = system.margin_rate_bound()
    return 2.0 * (system.margin_rate_estimate() if bound is None else bound) * dt


__all__ = [
    "DEFAULT_GAMMA",
    "DEFAULT_POLICIES",
    "FIELDS",
    "KINDS",
    "LOOKAHEAD_DISTURBANCES",
    "MAX_BACKUP_STEPS",
    "OUTSIDE_DOMAIN",
    "REMAINING",
    "FilterSettings",
    "default_threshold",
    "make_filter_settings",
    "resolve_policy",
    "settings_for_system",
]
