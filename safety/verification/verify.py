"""Verification of one value function: rollouts from sampled states, statistics, the guarantee.

:func:`verify` rolls out ``N`` given states (the same states for every value function being
compared), computes :func:`~safety.verification.metrics.violation_statistics`, and, unless told not to, bounds
the delta-level on a *fresh* sample drawn uniformly from ``{V(x, T) > delta}`` (a delta chosen from
one sample must be checked on another), giving the scenario ``eps`` for ``beta``.

For reach and reach-avoid problems the same steps run on the other side of zero: the scenario set
is ``{V(x, T) < -delta}``, the states from which the learned policy reaches the target in time (and,
for reach-avoid, without a collision) with confidence ``1 - beta``; every row names its ``problem``
kind, and its columns are the kind's (:data:`~safety.verification.metrics.KIND_COLUMNS`).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any

import torch

from reach.memory_check import require_memory
from reach.systems import ControlAffineSystem
from reach.threads import thread_policy
from reach.value_function import ValueFunction
from safety.verification.metrics import (
    KIND_COLUMNS,
    robust_level_search,
    scenario_epsilon,
    violation_statistics,
    wilson_interval,
)
from safety.verification.rollout import RolloutResult, RolloutSettings, rollout
from safety.verification.rollout_store import RolloutStore


@dataclass(frozen=True)
class VerifySettings:
    """What a verification run depends on; results are comparable only under equal settings."""

    samples: int = 100_000
    scenario_samples: int | None = None  # None: as many as ``samples``; 0: skip the guarantee
    beta: float = 1e-16
    seed: int = 0
    dt: float = 0.0025
    integrator: str = "euler"
    horizon: float | None = None
    chunk_size: int = 16384
    #: "bfloat16": networks' hidden products in bfloat16 during rollouts (faster, inexact; other
    #: value functions are always rolled out exactly, and each row records what was used)
    matmul_precision: str = "float32"
    #: robust scenario verification (Lin & Bansal, L4DC 2024, Thm 2): the largest {V > level} whose
    #: unsafe fraction is bounded by ``target_eps``; searched on ``robust_samples`` fresh
    #: uniform states, then checked on as many fresh states from the set (None: as many as
    #: ``scenario_samples`` resolves to; 0 skips). ``k = 0`` needs ln(1/beta) / target_eps samples
    #: (123k at the defaults), so the 100k default finds no level and says so in ``robust_error``.
    target_eps: float = 3e-4
    robust_samples: int | None = None
    #: the induced policy every rollout follows: "gradient" (the bang-bang u* of grad V, DeepReach's)
    #: or "greedy" (safety.value_policies.GreedyPolicy: the held candidate input that leaves the most value;
    #: about 2^m_u + 1 times the network work per step)
    policy: str = "gradient"
    #: the delta-level's check reuses the robust check's states that lie in {V > delta} and draws
    #: fresh ones only for the rest (:func:`_delta_check`): the same guarantees from about a
    #: third fewer rollouts under the card's protocol. Off by default, so rows keep their meaning.
    share_samples: bool = False
    #: how often the policy decides, in seconds (a whole multiple of dt), its input held in between;
    #: None: at every step. Every number then speaks of that held policy (RolloutSettings.control_period)
    control_period: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.samples, bool) or not isinstance(self.samples, int) or self.samples < 1:
            raise ValueError(f"samples must be a positive integer, got {self.samples!r}")
        n = self.scenario_samples
        if n is not None and (not isinstance(n, int) or n < 0):
            raise ValueError(f"scenario_samples must be an integer >= 0, got {self.scenario_samples!r}")
        if not (0.0 < self.beta < 1.0):
            raise ValueError(f"beta must lie in (0, 1), got {self.beta!r}")
        if not (0.0 < self.target_eps < 1.0):
            raise ValueError(f"target_eps must lie in (0, 1), got {self.target_eps!r}")
        if self.robust_samples is not None and (
            isinstance(self.robust_samples, bool) or not isinstance(self.robust_samples, int) or self.robust_samples < 0
        ):
            raise ValueError(f"robust_samples must be an integer >= 0, got {self.robust_samples!r}")
        if not isinstance(self.share_samples, bool):
            raise ValueError(f"share_samples must be True or False, got {self.share_samples!r}")
        self.rollout_settings(self.horizon)  # the rollout fields, checked where every rollout's are

    def rollout_settings(self, horizon: float | None, matmul_precision: str | None = None) -> RolloutSettings:
        """How each of this verification's rollouts simulates, from ``horizon`` (the resolved one)."""
        return RolloutSettings(
            horizon=horizon,
            dt=self.dt,
            integrator=self.integrator,
            policy=self.policy,
            chunk_size=self.chunk_size,
            matmul_precision=self.matmul_precision if matmul_precision is None else matmul_precision,
            control_period=self.control_period,
        )

    @property
    def fresh_samples(self) -> int:
        return self.samples if self.scenario_samples is None else self.scenario_samples

    @property
    def robust_sample_count(self) -> int:
        return self.fresh_samples if self.robust_samples is None else self.robust_samples

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def sample_states(system: ControlAffineSystem, n: int, seed: int) -> torch.Tensor:
    """``n`` uniform states from a seeded CPU generator: identical for every value function."""
    return system.sample_states(n, generator=torch.Generator().manual_seed(seed), dtype=torch.float32)


def values_at(
    vf: ValueFunction, x: torch.Tensor, t: float, chunk: int = 65536, device: str | torch.device = "cpu"
) -> torch.Tensor:
    """``V(x, t)`` in chunks on ``device``, returned as float32 on the CPU."""
    return torch.cat([vf.value(c.to(device), t).detach().float().cpu() for c in x.split(chunk)])


#: bytes a verification holds per sampled state and state dimension: the float32 states, the
#: rollout's working copies (the integrator's stages, the chunk's gradient) and the outcomes
BYTES_PER_STATE_AND_DIM = 4 * 6
#: bytes per sampled state besides: value, collided, collision and decision times (float64), and a
#: reach problem's reached flag and time
BYTES_PER_STATE = 4 + 1 + 8 + 8 + 16 + 1 + 8


def estimate_rollout_bytes(state_dim: int, settings: VerifySettings) -> int:
    """Peak memory of a verification on the host: the sampled states and their outcomes, plus the
    largest fresh sample (the scenario sample's, or the robust search's and its check)."""
    fresh = max(settings.fresh_samples, 2 * settings.robust_sample_count)
    states = settings.samples + fresh
    return int(states * (BYTES_PER_STATE_AND_DIM * state_dim + BYTES_PER_STATE))


def check_for_system(system: ControlAffineSystem, settings: VerifySettings) -> int:
    """Refuse, before sampling anything, settings that do not fit ``system``: a step longer than the
    system's horizon (when the settings leave the horizon to it), or a verification that needs more
    memory than is available; returns the memory estimate in bytes."""
    settings.rollout_settings(settings.horizon).for_system(system)
    what = f"verifying {settings.samples:,} states of {system.name} ({system.state_dim}D)"
    return require_memory(estimate_rollout_bytes(system.state_dim, settings), what, "use fewer --samples")


def sample_superlevel_set(
    vf: ValueFunction,
    level: float,
    n: int,
    seed: int,
    t: float,
    chunk: int = 65536,
    device: str | torch.device = "cpu",
    max_draws: int | None = None,
) -> tuple[torch.Tensor, int]:
    """``n`` states uniform on ``{V(x, t) > level}`` by rejection, and how many uniform draws it took.

    ``V`` is oriented by the system's kind (:meth:`~reach.systems.problem.ProblemKind.orient`): for a
    reach problem this is ``{V(x, t) < -level}``. Raises ``ValueError`` when the set is too small
    to fill after ``max_draws`` draws (default 100 n).
    """
    system = vf.system
    gen = torch.Generator().manual_seed(seed)
    max_draws = 100 * n if max_draws is None else max_draws
    kept: list[torch.Tensor] = []
    have = draws = 0
    batch = max(chunk, 2 * n)
    while have < n:
        if draws >= max_draws:
            raise ValueError(
                f"only {have} of {n} states found in {{V > {level:.4g}}} after {draws} uniform draws; "
                "the set is too small to bound"
            )
        x = system.sample_states(batch, generator=gen, dtype=torch.float32)
        draws += batch
        inside = x[system.problem.orient(values_at(vf, x, t, chunk, device)) > level]
        kept.append(inside)
        have += inside.shape[0]
    return torch.cat(kept)[:n], draws


def verify(
    vf: ValueFunction,
    states: torch.Tensor,
    settings: VerifySettings,
    device: str | torch.device = "cpu",
    progress: bool = True,
    store: RolloutStore | None = None,
    backend: Any = None,
) -> dict[str, Any]:
    """Violation statistics of ``vf`` on ``states`` and, if asked, the delta-level with its scenario bound.

    With a ``store`` (:class:`~safety.verification.rollout_store.RolloutStore`) every rollout is saved block by
    block and a repeated call loads what an interrupted one finished: the same row, resumed. With a
    ``backend`` (:class:`~safety.verification.sharding.RayBlocks`) the blocks run on its workers: the same row.
    Unless the caller chose a thread count, torch uses the cores other processes leave free while
    it runs (:func:`reach.threads.thread_policy`)."""
    check_for_system(vf.system, settings)
    with thread_policy():
        return _verify(vf, states, settings, device, progress, store, backend)


def _rollout(
    store: RolloutStore | None, name: str, vf: ValueFunction, states: torch.Tensor, common: dict[str, Any]
) -> RolloutResult:
    """One of a verification's rollouts (``name``: which), through the store where there is one and
    on the block backend where ``common`` names one."""
    common = dict(common)
    backend = common.pop("backend", None)
    if store is not None:
        return store.rollout(name, vf, states, backend=backend, **common)
    if backend is not None:
        return backend.rollout(vf, states, **common)
    return rollout(vf, states, **common)


def _verify(
    vf: ValueFunction,
    states: torch.Tensor,
    settings: VerifySettings,
    device: str | torch.device,
    progress: bool,
    store: RolloutStore | None = None,
    backend: Any = None,
) -> dict[str, Any]:
    start = time.perf_counter()
    horizon = vf.system.horizon if settings.horizon is None else settings.horizon
    precision = settings.matmul_precision if hasattr(vf, "with_matmul_dtype") else "float32"
    common = {"settings": settings.rollout_settings(horizon, precision), "device": device, "progress": progress}
    if backend is not None:
        common["backend"] = backend
    result = _rollout(store, "samples", vf, states, common)
    kind = vf.system.kind
    row: dict[str, Any] = {"problem": kind}
    row.update(violation_statistics(result.oriented_value, result.failed, kind, result.collided))
    row["matmul_precision"] = precision
    failures = int(result.failed.sum())
    ci = "collision_ci" if kind == "avoid" else "failure_ci"
    row[f"{ci}_low"], row[f"{ci}_high"] = wilson_interval(failures, result.num_states)
    row["rollout_seconds"] = result.wall_time
    row["work_fraction"] = result.work_fraction
    row["state_steps_per_second"] = result.state_steps / max(result.wall_time, 1e-12)
    row.update(scenario_states=0, scenario_failures=None, eps=math.nan, scenario_volume=math.nan)
    robust: tuple[dict[str, Any], RolloutResult | None] | None = None
    if settings.robust_sample_count:
        # first where the delta-level's check may reuse the robust check's states
        robust = _robust_scenario_set(vf, settings, horizon, common, device, store)
    if settings.fresh_samples:
        reused = None
        # only a level at or below delta makes {V > delta} part of the set the robust check sampled
        check = None if robust is None else robust[1]
        if settings.share_samples and check is not None and robust[0]["robust_level"] <= row["delta"]:
            reused = check.failed[check.oriented_value > row["delta"]]
        try:
            k, n, used = _delta_check(vf, row["delta"], settings, horizon, common, device, store, reused)
        except ValueError as err:
            row["scenario_error"] = str(err)
        else:
            row.update(
                scenario_states=n,
                scenario_failures=k,
                eps=scenario_epsilon(k, n, settings.beta) if k < n else 1.0,
                scenario_volume=row[KIND_COLUMNS[kind][3]],
            )
            if settings.share_samples:
                row["scenario_reused"] = used
    if robust is not None:
        row.update(robust[0])
    row["wall_time"] = time.perf_counter() - start
    return row


def _delta_check(
    vf: ValueFunction,
    delta: float,
    settings: VerifySettings,
    horizon: float,
    common: dict[str, Any],
    device: str | torch.device,
    store: RolloutStore | None,
    reused: torch.Tensor | None,
) -> tuple[int, int, int]:
    """The delta-level's check: failures among ``N`` states uniform on ``{V > delta}``, how many
    were checked, and how many of them were reused.

    Without ``reused`` all ``N`` are fresh (seed + 1). With it (:attr:`VerifySettings.share_samples`),
    ``reused`` holds the outcomes (failed or not, in sampling order) of the robust check's states
    inside ``{V > delta}``; the first ``N`` of them count, and fresh states (seed + 1) fill the rest. Why this is
    sound: the robust check's states are i.i.d. uniform on ``{V > level}`` given the level, so those
    of them in ``{V > delta}`` (a subset when ``level <= delta``), given how many there are, are
    i.i.d. uniform on ``{V > delta}``, and delta was chosen on another, independent sample. The
    count depends on values only, never on outcomes. So the ``N`` states are the i.i.d. sample of
    ``{V > delta}`` the scenario bound needs, whichever draw each came from; the two guarantees
    each keep their ``1 - beta``."""
    n = settings.fresh_samples
    used = 0 if reused is None else min(n, int(reused.shape[0]))
    failures = 0 if reused is None else int(reused[:used].sum())
    if used < n:
        fresh, _ = sample_superlevel_set(vf, delta, n - used, settings.seed + 1, horizon, device=device)
        failures += int(_rollout(store, "certify", vf, fresh, common).failed.sum())
    return failures, n, used


def robust_scenario_set(
    vf: ValueFunction,
    settings: VerifySettings,
    horizon: float,
    common: dict[str, Any],
    device: str | torch.device,
    store: RolloutStore | None = None,
) -> dict[str, Any]:
    """The robust scenario verification's columns (see :func:`_robust_scenario_set`)."""
    return _robust_scenario_set(vf, settings, horizon, common, device, store)[0]


def _robust_scenario_set(
    vf: ValueFunction,
    settings: VerifySettings,
    horizon: float,
    common: dict[str, Any],
    device: str | torch.device,
    store: RolloutStore | None = None,
) -> tuple[dict[str, Any], RolloutResult | None]:
    """Robust scenario verification (Lin & Bansal, L4DC 2024, Thm 2), in two independent samples.

    1. *Search*: ``N`` fresh uniform states (seed + 2) are rolled out, and
       :func:`~safety.verification.metrics.robust_level_search` picks the lowest level whose superlevel set they
       bound at ``target_eps``; the set's volume is estimated from the same uniform sample.
    2. *Certification*: ``N`` fresh states from ``{V > level}`` (seed + 3), rolled out; their ``k``
       failures give ``robust_eps``, the bound that holds with confidence ``1 - beta`` (a level
       chosen on one sample means nothing until a second one bounds it).

    Returns the columns, and the check's outcomes (None where no level was found)."""
    n = settings.robust_sample_count
    out: dict[str, Any] = {
        "robust_target_eps": settings.target_eps,
        "robust_samples": n,
        "robust_level": math.nan,
        "robust_eps": math.nan,
        "robust_failures": None,
        "robust_scenario_volume": math.nan,
    }
    search_states = sample_states(vf.system, n, settings.seed + 2)
    search = _rollout(store, "robust-search", vf, search_states, common)
    found = robust_level_search(search.oriented_value, search.failed, settings.target_eps, settings.beta)
    if found is None:
        need = math.ceil(math.log(1 / settings.beta) / settings.target_eps)
        out["robust_error"] = (
            f"no level is bounded at eps {settings.target_eps:g} by {n} samples (k = 0 needs at least {need})"
        )
        return out, None
    level, inside, _ = found
    try:
        fresh, _ = sample_superlevel_set(vf, level, n, settings.seed + 3, horizon, device=device)
    except ValueError as err:
        out["robust_error"] = str(err)
        return out, None
    check = _rollout(store, "robust-check", vf, fresh, common)
    k = int(check.failed.sum())
    out.update(
        robust_level=level,
        robust_eps=scenario_epsilon(k, check.num_states, settings.beta) if k < check.num_states else 1.0,
        robust_failures=k,
        robust_scenario_volume=inside / n,
    )
    return out, check
