"""The safety filter as environment wrappers: Gymnasium, Gymnasium vector, PettingZoo parallel.

Each adapter reads the environment's exact (float64) state, asks :class:`~safety.filters.base.SafetyFilter`
for the input to apply, and steps the wrapped environment with it. Actions stay in the
environments' normalised units ([-1, 1] per turn rate): a kept action passes through unchanged and
a replaced one is ``u*`` normalised (a box corner, so exactly +-1, or 0 on a tie).

Time-to-go: ``time_to_go=None`` (default) evaluates ``V`` at the system's horizon, the fixed tube the
value function was trained for; a number fixes another horizon; ``"remaining"`` uses the time left
in the episode (``horizon - elapsed``, floored at 0). Reach kinds (``"reach"``, ``"reach-avoid"``)
have a deadline, the end of the episode: ``None`` means ``"remaining"`` there, so the time-to-go
counts down every step, a fixed number is refused, and once it has run out the filter applies
``u*`` (it can certify nothing; :mod:`safety.filters.base`).

Settings: the filter's options are one :class:`~safety.filters.settings.FilterSettings`, given whole
(``SafetyFilterWrapper(env, vf, settings=FilterSettings(kind="lookahead"))``) or field by field as
keywords (``SafetyFilterWrapper(env, vf, kind="lookahead")``); its defaults are the ones below.

Filters: ``kind="switch"`` (default, :mod:`safety.filters.switch`), ``"lookahead"`` (predicts one env
step with the env's ``dt`` and integrator, then ``backup_horizon`` seconds of the backup policy,
default the system's horizon, along the ``backup_disturbance`` paths, default ``"robust"``;
:mod:`safety.filters.lookahead`) or ``"smooth"`` (``gamma``: the barrier rate; :mod:`safety.filters.smooth`).

Backup input: ``policy="greedy"`` applies :class:`~safety.value_policies.GreedyPolicy`'s input where a
filter overrides the nominal input, ``"gradient"`` the gradient's ``u*``; ``None`` (default) takes
the kind's default, greedy for the switch, gradient for the lookahead and the smooth filter (each
kind's module says why).

Threshold: a switch or smooth filter that acts once per environment step (zero-order hold) lets
``V`` fall by up to about ``|dl/dt|_max * dt`` before it can react, so their default threshold
(``threshold=None``) is ``2 * margin_rate_bound * dt`` (0.06 for Air3D at dt = 0.02; systems that
declare no bound use a rate sampled from their own physics, :meth:`margin_rate_estimate`).
At threshold 0 a switch filter lets a state ride the BRT boundary and slip in between decisions.
The lookahead filter checks the state after the step and a rollout of the backup policy after it,
so its default threshold is 0 (measured, each kind at each threshold: docs/results/filters.md).

Certificate: ``certificate=CERT`` (a :class:`~safety.formal.certificate.Certificate` or its ``.npz`` file,
:mod:`safety.formal.verifier`) filters with :class:`~safety.formal.certified_filter.CertifiedFilter` instead: inside
the certified set the nominal action is kept only where it is proven to stay in the set, otherwise
the certificate's backup input is applied, so an episode that starts in the set stays safe for all
time, by proof. The certificate is re-verified for ``value_function`` first, and refused, naming the
mismatch, when it was made for another model or system, when the env steps with another ``dt`` or
integrator than it assumed, or when the scene adds process noise (an effect it does not cover).
The filter settings do not apply to it, and are refused beside it. ``info`` then also holds
``filter_certified``: whether the pre-step state lay in the certified set.

``info`` gains ``filter_value`` (``V`` at the pre-step state), ``filter_intervened``,
``nominal_action`` and ``applied_action`` (normalised units); the vector wrapper's also
``filter_infeasible`` (the smooth filter's, else None). :func:`filter_step_info` builds the
``filter_*`` entries of every wrapper from the filter's info.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import VectorWrapper
from pettingzoo.utils.wrappers import BaseParallelWrapper

from reach.value_function import ValueFunction, check_time_coverage
from reach_envs.spaces import inputs_of_actions
from safety.filters.base import FilterInfo, SafetyFilter, require_served_kind
from safety.filters.settings import DEFAULT_GAMMA, REMAINING, FilterSettings, default_threshold, make_filter_settings
from safety.value_loading import as_value_function
from training import pretrained

__all__ = [
    "DEFAULT_GAMMA",
    "SafetyFilterParallelWrapper",
    "SafetyFilterVectorWrapper",
    "SafetyFilterWrapper",
    "default_threshold",
    "filter_step_info",
]


def filter_step_info(info: Any, batched: bool = False, source_trusted: bool | None = None) -> dict[str, Any]:
    """The ``filter_*`` entries of a wrapper's step ``info``, from the filter's info (a
    :class:`FilterInfo`, or a certificate's :class:`~safety.formal.certified_filter.CertifiedInfo`):
    ``filter_value`` (``V`` at the pre-step state), ``filter_intervened``, ``filter_certified``
    where the filter is a certificate's, and ``filter_source_trusted``: whether the value function's
    source passed its model card's trust bar (None: the user's own value function, which has no card).
    One state (``batched=False``) as Python numbers; a batch (the vector wrapper) as arrays, with
    ``filter_infeasible`` too (the smooth filter's, else None)."""
    if batched:
        infeasible = getattr(info, "infeasible", None)
        entries = {
            "filter_value": info.value.numpy(),
            "filter_intervened": info.intervened.numpy(),
            "filter_infeasible": None if infeasible is None else infeasible.numpy(),
        }
    else:
        entries = {"filter_value": float(info.value), "filter_intervened": bool(info.intervened)}
    if hasattr(info, "certified"):
        entries["filter_certified"] = info.certified.numpy() if batched else bool(info.certified)
    entries["filter_source_trusted"] = source_trusted
    return entries


class _UnitAdapter:
    """What every adapter shares: the value function served to the env's system, and the env's
    normalised actions in and out of the filter (a kept action passes through unchanged, a replaced
    one is the filter's input normalised). Subclasses decide in :meth:`_decide`."""

    filter: Any
    settings: FilterSettings | None

    def _serve(self, system: Any, value_function: ValueFunction | str, device: str) -> ValueFunction:
        """``value_function`` loaded for ``system`` on ``device``, refused (naming both) where it
        solves another problem kind or another system's physics; also sets the action units."""
        if isinstance(value_function, ValueFunction):  # a kind mismatch names both kinds, before physics
            require_served_kind(system, value_function.system)
        vf = as_value_function(
            value_function, system, device, "value function (the environment simulates another system)"
        )
        self.bounds = system.control_bounds
        self.centre = np.array(system.control_bounds.center)
        self.half = np.array(system.control_bounds.half_width)
        return vf

    def _decide(self, x: torch.Tensor, elapsed: np.ndarray | float, u_nominal: torch.Tensor) -> tuple[Any, Any]:
        """``(applied inputs, info)`` of the filter for float64 states and nominal inputs."""
        raise NotImplementedError

    def apply(self, state: np.ndarray, elapsed: np.ndarray | float, action: np.ndarray) -> tuple[np.ndarray, Any]:
        """Filtered normalised actions for float64 ``state`` and normalised ``action`` (same batch)."""
        a = np.asarray(action, dtype=np.float64)
        if not np.isfinite(a).all():
            raise ValueError(f"action contains a non-finite value (NaN or inf): {action!r}")
        x = torch.as_tensor(state, dtype=torch.float64)
        u_nominal = torch.as_tensor(inputs_of_actions(a, self.bounds), dtype=torch.float64)
        applied_u, info = self._decide(x, elapsed, u_nominal)
        if not bool(torch.isfinite(applied_u).all()):  # the filter's own value, not the caller's action
            raise ValueError(
                "the safety filter computed a non-finite input (NaN or inf) from its value function; "
                "the nominal action was finite and is not the cause"
            )
        star = (applied_u.numpy() - self.centre) / self.half
        keep = ~info.intervened.numpy().reshape(a.shape[:-1])  # one state: the filter's batch of one
        applied = np.where(keep[..., None], a, star)
        dtype = np.asarray(action).dtype
        return (applied.astype(dtype) if dtype.kind == "f" else applied), info


class _Adapter(_UnitAdapter):
    """The time-to-go logic of the three wrappers around a :class:`SafetyFilter`."""

    def __init__(
        self, system: Any, value_function: ValueFunction | str, scene: Any, device: str, settings: FilterSettings
    ) -> None:
        episode_horizon = scene.episode_horizon
        threshold = settings.threshold_for(system, scene.dt)  # None: the rule for a filter acting every dt
        vf = self._serve(system, value_function, device)
        self.filter = SafetyFilter(
            vf,
            settings=make_filter_settings(settings, threshold=threshold),
            dt=scene.dt,
            integrator=scene.integrator,
            system=system,
        )
        # the times the filter will ask for, checked now rather than mid-episode; a reach task's
        # time-to-go counts down to its deadline (a fixed one was refused by the filter)
        time_to_go = settings.time_to_go
        if time_to_go is None and system.problem.reaches:
            time_to_go = REMAINING
        if time_to_go is None:
            check_time_coverage(vf, vf.system.horizon, vf.system.horizon, "the filter (time_to_go=None)")
        elif time_to_go == REMAINING:
            check_time_coverage(vf, 0.0, episode_horizon, "the filter (time_to_go='remaining')")
        else:
            check_time_coverage(vf, float(time_to_go), float(time_to_go), f"the filter (time_to_go={time_to_go})")
        self.settings = settings
        self.time_to_go = time_to_go
        self.episode_horizon = episode_horizon

    def times(self, elapsed: np.ndarray | float) -> float | torch.Tensor:
        """The time-to-go the filter evaluates ``V`` at, after ``elapsed`` seconds of the episode."""
        if self.time_to_go is None:
            return self.filter.system.horizon
        if self.time_to_go == REMAINING:
            return torch.as_tensor(np.maximum(self.episode_horizon - np.asarray(elapsed, dtype=np.float64), 0.0))
        return float(self.time_to_go)

    def _decide(
        self, x: torch.Tensor, elapsed: np.ndarray | float, u_nominal: torch.Tensor
    ) -> tuple[torch.Tensor, FilterInfo]:
        _, info = self.filter(x, self.times(elapsed), u_nominal)
        return info.applied, info


class _CertifiedAdapter(_UnitAdapter):
    """The adapter of a certificate: :class:`~safety.formal.certified_filter.CertifiedFilter`, refused where
    the env breaks one of the certificate's assumptions."""

    def __init__(self, system: Any, value_function: ValueFunction | str, scene: Any, certificate: Any) -> None:
        # lazy: the certificate machinery (bounds, intervals) only for a certified wrapper
        from safety.formal.certificate import Certificate, load_certificate
        from safety.formal.certified_filter import CertifiedFilter

        label = str(certificate) if not isinstance(certificate, Certificate) else "the certificate"
        cert = certificate if isinstance(certificate, Certificate) else load_certificate(certificate)
        assumed = cert.settings
        if not math.isclose(float(scene.dt), assumed.dt, rel_tol=1e-12) or scene.integrator != assumed.integrator:
            raise ValueError(
                f"{label} proves steps of dt {assumed.dt:g} ({assumed.integrator}); the environment steps "
                f"dt {scene.dt:g} ({scene.integrator}): make the env with the certificate's dt and integrator"
            )
        if scene.process_noise is not None and bool(np.any(np.asarray(scene.process_noise) != 0)):
            raise ValueError(
                f"{label} covers the model's dynamics and disturbances only; the scene adds process noise "
                f"{scene.process_noise!r}, which it does not"
            )
        self.filter = CertifiedFilter(cert, self._serve(system, value_function, "cpu"))
        self.settings = None

    def _decide(self, x: torch.Tensor, elapsed: np.ndarray | float, u_nominal: torch.Tensor) -> tuple[Any, Any]:
        return self.filter(x, u_nominal)


def _env_id(env: Any) -> str | None:
    """The Gymnasium id of ``env`` (from its spec, else from its named scene), or None."""
    from reach_envs import ENV_SCENES  # lazy: registers the envs only when an id is looked up

    spec = getattr(env, "spec", None)
    if getattr(spec, "id", None):
        return spec.id
    scene = getattr(getattr(env.unwrapped, "scene", None), "name", None)
    return next((env_id for env_id, name in ENV_SCENES.items() if name == scene), None)


class _FilterAdapterMixin:
    """The one set-up every wrapper shares: its settings, and an :class:`_Adapter` for the wrapped
    env's system.

    ``threshold``, ``time_to_go`` and any other :class:`FilterSettings` field given by keyword
    (``kind="lookahead"``) replace that field of ``settings``
    (:func:`~safety.filters.settings.make_filter_settings`); ``None`` leaves it as ``settings`` has it.
    """

    _adapter: _UnitAdapter

    def __init__(
        self,
        env: Any,
        value_function: ValueFunction | str | None = None,
        threshold: float | None = None,
        time_to_go: float | str | None = None,
        device: str = "cpu",
        *,
        settings: FilterSettings | None = None,
        certificate: Any = None,
        allow_untrusted: bool = False,
        **options: Any,
    ) -> None:
        if not isinstance(allow_untrusted, bool):
            raise ValueError(f"allow_untrusted must be True or False, got {allow_untrusted!r}")
        self._allow_untrusted = allow_untrusted
        if certificate is not None:
            given = {"threshold": threshold, "time_to_go": time_to_go, "settings": settings, **options}
            named = sorted(k for k, v in given.items() if v is not None)
            if named:
                raise ValueError(f"a certificate decides by its own proof; filter settings do not apply to it: {named}")
            if device != "cpu":
                raise ValueError(f"a certified filter bounds its boxes on the CPU; got device {device!r}")
        settings = make_filter_settings(settings, threshold=threshold, time_to_go=time_to_go, **options)
        self._record(value_function, device, settings, certificate)
        super().__init__(env)  # the wrapper base class of the env kind
        self._attach_filter(env, value_function, device, settings, certificate)

    def _record(
        self, value_function: ValueFunction | str | None, device: str, settings: FilterSettings, certificate: Any
    ) -> None:
        """Where a wrapper that records its constructor's arguments does so (Gymnasium's)."""

    def _attach_filter(
        self,
        env: Any,
        value_function: ValueFunction | str | None,
        device: str,
        settings: FilterSettings,
        certificate: Any = None,
    ) -> None:
        base = env.unwrapped
        if value_function is None:  # nothing picks an untrusted model: refused unless allow_untrusted
            value_function = pretrained.for_env(_env_id(env), base.system, self._allow_untrusted)
            found = pretrained.card_for_env(_env_id(env), base.system)
            self.source_verdict = None if found is None else found.verdict
        else:
            self.source_verdict = pretrained.source_verdict(value_function)
        if certificate is not None:
            self._adapter = _CertifiedAdapter(base.system, value_function, base.scene, certificate)
        else:
            self._adapter = _Adapter(base.system, value_function, base.scene, device, settings)

    @property
    def source_trusted(self) -> bool | None:
        """Whether the value function's source passed its model card's trust bar
        (:attr:`source_verdict`); None for a value function of the user's own, which has no card."""
        return None if self.source_verdict is None else self.source_verdict.passes

    @property
    def safety_filter(self) -> Any:
        """The filter in use: a :class:`SafetyFilter` (its ``threshold`` may be changed between steps),
        or the :class:`~safety.formal.certified_filter.CertifiedFilter` of a certificate."""
        return self._adapter.filter

    @property
    def filter_settings(self) -> FilterSettings | None:
        """The :class:`FilterSettings` this wrapper was made with (``threshold=None``: the default
        rule, resolved in ``safety_filter.threshold``); None for a certificate's filter."""
        return self._adapter.settings


class SafetyFilterWrapper(_FilterAdapterMixin, gym.Wrapper, gym.utils.RecordConstructorArgs):
    """A Gymnasium env whose actions pass through a safety filter (``kind``: switch, lookahead, smooth).

    ``SafetyFilterWrapper(env, value_function=None, threshold=None, time_to_go=None, device="cpu",
    *, settings=None, **options)``: the filter's options are one
    :class:`~safety.filters.settings.FilterSettings` (``settings``), or its fields by keyword.
    Without ``value_function`` the filter uses the model shipped for the env
    (:func:`training.pretrained.for_env`: ``SafetyFilterWrapper(gym.make("Air3D-v0"))`` filters with
    ``"pretrained:air3d"``); an env no shipped model fits raises ``ValueError``.
    ``value_function`` may be a path (run directory, checkpoint, ``.npz``), which keeps
    ``env.spec`` serialisable, so ``gym.make(env.spec)`` rebuilds the wrapped env: the spec records
    the settings field by field, as keywords.
    """

    def _record(
        self, value_function: ValueFunction | str | None, device: str, settings: FilterSettings, certificate: Any
    ) -> None:
        recorded = {"certificate": certificate} if certificate is not None else settings.keywords()
        if self._allow_untrusted:  # the opt-in travels with the wrapper's recorded arguments
            recorded["allow_untrusted"] = True
        gym.utils.RecordConstructorArgs.__init__(self, value_function=value_function, device=device, **recorded)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        base = self.env.unwrapped
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {a.shape}")
        applied, info = self._adapter.apply(base.state, base.time, np.asarray(action))
        obs, reward, terminated, truncated, step_info = self.env.step(applied)
        entries = filter_step_info(info, source_trusted=self.source_trusted)
        step_info.update(entries, nominal_action=np.asarray(action), applied_action=applied)
        return obs, reward, terminated, truncated, step_info


class SafetyFilterVectorWrapper(_FilterAdapterMixin, VectorWrapper):
    """The filter over a :class:`~reach_envs.vector.ReachVectorEnv`, batched over sub-environments."""

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict]:
        base = self.env.unwrapped
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != self.action_space.shape:
            raise ValueError(f"actions must have shape {self.action_space.shape}, got {a.shape}")
        applied, info = self._adapter.apply(base.state, base.elapsed, np.asarray(actions))
        obs, reward, terminated, truncated, step_info = self.env.step(applied)
        step_info = dict(step_info)
        entries = filter_step_info(info, batched=True, source_trusted=self.source_trusted)
        step_info.update(entries, nominal_action=np.asarray(actions), applied_action=applied)
        return obs, reward, terminated, truncated, step_info


class SafetyFilterParallelWrapper(_FilterAdapterMixin, BaseParallelWrapper):
    """The filter over a PettingZoo parallel env: the joint nominal action is filtered as one input.

    Each agent's action holds the inputs it acts (a car's turn rate; NarrowPassage's drivers, their
    acceleration and steering rate). Agents that are no longer live contribute the centre of their
    box (zero turn rate) to the joint nominal input, as the environment applies for them.
    """

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        base = self.env.unwrapped
        joint = np.zeros(base.system.control_dim)
        for agent, action in actions.items():
            a = np.asarray(action, dtype=np.float64)
            k = list(base.control_indices(agent))
            if a.shape != (len(k),):
                raise ValueError(f"action of {agent!r} must have shape ({len(k)},), got {a.shape}")
            joint[k] = a
        applied, info = self._adapter.apply(base.full_state, base.elapsed, joint)
        filtered = {agent: applied[list(base.control_indices(agent))].astype(np.float32) for agent in actions}
        obs, rewards, terminations, truncations, infos = self.env.step(filtered)
        # the joint input's verdict, the same for every agent
        shared = filter_step_info(info, source_trusted=self.source_trusted)
        for agent in infos:
            k = list(base.control_indices(agent))
            one = len(k) == 1  # a car's turn rate reads as a number, an agent of several inputs as an array
            infos[agent] = {
                **infos[agent],
                **shared,
                "nominal_action": float(joint[k[0]]) if one else joint[k].copy(),
                "applied_action": float(applied[k[0]]) if one else applied[k].copy(),
            }
        return obs, rewards, terminations, truncations, infos
