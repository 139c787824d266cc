"""What a safety filter buys and what it costs, measured over episodes of a goal-seeking task.

:func:`evaluate_filters` runs ``N`` episodes of a scene in one vector environment per
configuration, every configuration from the same seeded initial states and task goals: the nominal
policy alone (``value_function=None``) and under the least-restrictive filter for each value function
and threshold. Per configuration it reports the collision rate (95 % Wilson interval), the
intervention rate (filtered steps / running steps), the mean absolute change of the input
(physical units, per input and step), the goal-reaching rate and mean time, and the wall time.
:func:`evaluate_filter_parallel` computes the same numbers through the PettingZoo parallel
environment, episode by episode (a cross-check of the two paths).

An episode ends at its first collision (the environments' ``terminate_on_collision``), on leaving the
arena, or at the scene's horizon; the filter evaluates ``V`` at the time-to-go it is given (default:
the value function's own horizon, a fixed-horizon filter).
"""

from __future__ import annotations

import copy
import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from reach.locking import exclusive_lock
from reach.value_function import ValueFunction
from reach_envs.scenes import Scene, make_scene
from reach_envs.vector import ReachVectorEnv
from safety.filter import DEFAULT_GAMMA, check_filter_settings, resolve_policy
from safety.metrics import wilson_interval
from studies.tables import markdown_table, merge_rows, write_results
from studies.tasks import GoalTask, NominalPolicy, make_task
from safety.value_policies import worst_case_disturbance
from safety.wrappers import SafetyFilterParallelWrapper, SafetyFilterVectorWrapper, default_threshold


@dataclass
class FilterConfig:
    """One configuration: a label, a value function (``None``: nominal policy alone), a threshold,
    the filter kind (``switch``, ``lookahead``, ``smooth``), the smooth filter's ``gamma`` and the
    lookahead's ``backup_horizon`` (seconds; ``None``: the system's horizon), and the backup input's
    ``policy`` (``"gradient"``, ``"greedy"``, or ``None``: the kind's default)."""

    label: str
    value_function: ValueFunction | None = None
    threshold: float | None = None
    kind: str = "switch"
    gamma: float = DEFAULT_GAMMA
    backup_horizon: float | None = None
    backup_disturbance: str = "robust"
    policy: str | None = None

    def __post_init__(self) -> None:
        if self.value_function is not None:  # refused before any episode runs
            check_filter_settings(self.kind, self.gamma, self.backup_horizon, self.backup_disturbance, self.policy)

    def filter_options(self) -> dict[str, Any]:
        """The keyword arguments every filter wrapper takes for this configuration's filter."""
        return {
            "kind": self.kind,
            "gamma": self.gamma,
            "backup_horizon": self.backup_horizon,
            "backup_disturbance": self.backup_disturbance,
            "policy": self.policy,
        }


class _Tally:
    """Per-configuration counters over running episodes."""

    def __init__(self, n: int) -> None:
        self.collided = np.zeros(n, dtype=bool)
        self.active = np.ones(n, dtype=bool)
        self.running_steps = 0
        self.interventions = 0
        self.infeasible = 0
        self.change = 0.0
        self.variation = np.zeros(n)  # total variation of the applied input, per episode
        self.min_margin = np.full(n, np.inf)  # smallest l(x) reached, per episode
        self._last: np.ndarray | None = None

    def step(
        self,
        collision: np.ndarray,
        intervened: np.ndarray | None,
        change: np.ndarray,
        applied: np.ndarray,
        margin: np.ndarray,
        infeasible: np.ndarray | None = None,
    ) -> None:
        a = self.active
        self.collided |= collision & a
        self.running_steps += int(a.sum())
        if intervened is not None:
            self.interventions += int((intervened & a).sum())
        if infeasible is not None:
            self.infeasible += int((infeasible & a).sum())
        self.change += float(change[a].sum())
        if self._last is not None:
            self.variation += np.where(a, np.abs(applied - self._last).sum(axis=-1), 0.0)
        self._last = applied
        self.min_margin = np.where(a, np.minimum(self.min_margin, margin), self.min_margin)

    def row(self, config: FilterConfig, task: GoalTask, inputs: int, threshold: float | None, wall: float) -> dict:
        n = len(self.collided)
        hits = int(self.collided.sum())
        low, high = wilson_interval(hits, n)
        reached = task.reached & ~self.collided
        lookahead = config.value_function is not None and config.kind == "lookahead"
        row = {
            "label": config.label,
            "filtered": config.value_function is not None,
            "threshold": threshold,
            "episodes": n,
            "collision_rate": hits / n,
            "collision_ci_low": low,
            "collision_ci_high": high,
            "intervention_rate": self.interventions / max(1, self.running_steps),
            "mean_input_change": self.change / max(1, self.running_steps * inputs),
            "total_variation": float(self.variation.mean()),
            "min_margin": float(self.min_margin.min()),
            "mean_min_margin": float(self.min_margin.mean()),
            "infeasible_rate": self.infeasible / max(1, self.running_steps),
            "kind": config.kind if config.value_function is not None else None,
            "gamma": config.gamma if config.value_function is not None and config.kind == "smooth" else None,
            "backup_horizon": _backup_horizon(config) if lookahead else None,
            "backup_disturbance": config.backup_disturbance if lookahead else None,
            "policy": resolve_policy(config.kind, config.policy) if config.value_function is not None else None,
            "goal_rate": float(reached.mean()) if task.has_goal else float("nan"),
            "mean_goal_time": float(np.nanmean(task.reach_time[reached])) if reached.any() else float("nan"),
            "wall_time": wall,
            "collided_episodes": [int(i) for i in np.flatnonzero(self.collided)[:20]],
        }
        return _labelled(row)


def _scene(scene: str | Scene, overrides: dict[str, Any] | None) -> Scene:
    return make_scene(scene, **(overrides or {}))


def evaluate_filters(
    scene: str | Scene,
    configs: Sequence[FilterConfig],
    episodes: int = 1000,
    seed: int = 0,
    time_to_go: float | str | None = None,
    task: GoalTask | None = None,
    scene_overrides: dict[str, Any] | None = None,
    initial_states: np.ndarray | None = None,
) -> list[dict[str, Any]]:
    """Rows of metrics, one per configuration, from ``episodes`` vectorised episodes each.

    ``initial_states`` ``(episodes, n)`` replaces the scene's sampler (e.g. states drawn outside a
    BRT with :func:`outside_states`); otherwise sub-environment ``i`` is seeded ``seed + i``.
    """
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    sc = _scene(scene, scene_overrides)
    system = sc.system
    task = task if task is not None else make_task(system)
    half = np.array(system.control_bounds.half_width)
    if initial_states is not None and np.shape(initial_states) != (episodes, system.state_dim):
        raise ValueError(
            f"initial_states must have shape ({episodes}, {system.state_dim}), got {np.shape(initial_states)}"
        )
    rows = []
    for config in configs:
        start = time.perf_counter()
        base = ReachVectorEnv(episodes, sc)
        env = base
        threshold = None
        if config.value_function is not None:
            env = SafetyFilterVectorWrapper(
                base,
                config.value_function,
                config.threshold,
                time_to_go,
                **config.filter_options(),
            )
            threshold = env.safety_filter.threshold
        options = None if initial_states is None else {"state": initial_states}
        env.reset(seed=seed, options=options)
        task.reset(base.state, np.random.default_rng(seed))
        tally = _Tally(episodes)
        for k in range(sc.max_steps):
            nominal = task.nominal_actions(base.state).astype(np.float32)
            _, _, terminated, truncated, info = env.step(nominal)
            applied = info.get("applied_action", nominal)
            physical = np.asarray(applied, dtype=np.float64) * half
            change = np.abs(physical - nominal * half).sum(axis=1)
            tally.step(
                info["collision"],
                info.get("filter_intervened"),
                change,
                physical,
                info["margin"],
                info.get("filter_infeasible"),
            )
            task.advance(base.state, info["control"], sc.dt, tally.active & ~info["collision"], (k + 1) * sc.dt)
            tally.active &= ~(terminated | truncated)
            if not tally.active.any():
                break
        env.close()
        rows.append(tally.row(config, task, system.control_dim, threshold, time.perf_counter() - start))
    return rows


def _backup_horizon(config: FilterConfig) -> float:
    """The lookahead's backup rollout in seconds, its default (the system's horizon) resolved."""
    return config.value_function.system.horizon if config.backup_horizon is None else float(config.backup_horizon)


def _labelled(row: dict[str, Any]) -> dict[str, Any]:
    """``value_function`` = the configuration's name; ``label`` adds the threshold when filtered."""
    name = row["label"]
    threshold = row["threshold"]
    if threshold is None:
        return {**row, "value_function": name, "label": name}
    kind = "" if row.get("kind") in (None, "switch") else f" {row['kind']}"
    gamma = f" g{row['gamma']:g}" if row.get("gamma") is not None else ""
    policy = " greedy" if row.get("policy") == "greedy" else ""
    return {**row, "value_function": name, "label": f"{name}{kind}{policy} @ {threshold:.3g}{gamma}"}


def evaluate_filter_parallel(
    scene: str | Scene,
    config: FilterConfig,
    episodes: int = 100,
    seed: int = 0,
    time_to_go: float | str | None = None,
    task: GoalTask | None = None,
    scene_overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The same metrics through the PettingZoo parallel env (episode ``i`` seeded ``seed + i``)."""
    from reach_envs.parallel import MultiVehicleParallelEnv

    sc = _scene(scene, scene_overrides)
    system = sc.system
    task = task if task is not None else make_task(system)
    half = np.array(system.control_bounds.half_width)
    start = time.perf_counter()
    tally = _Tally(episodes)
    reached = np.zeros(episodes, dtype=bool)
    reach_time = np.full(episodes, np.nan)
    threshold = None
    for i in range(episodes):
        base = MultiVehicleParallelEnv(sc)
        env: Any = base
        if config.value_function is not None:
            env = SafetyFilterParallelWrapper(
                base,
                config.value_function,
                config.threshold,
                time_to_go,
                **config.filter_options(),
            )
            threshold = env.safety_filter.threshold
        env.reset(seed=seed + i)
        rng = np.random.default_rng(seed)
        task.reset(base.full_state[None], rng)
        one = _Tally(1)
        for k in range(sc.max_steps):
            nominal = task.nominal_actions(base.full_state[None]).astype(np.float32)[0]
            actions = {
                agent: nominal[base.control_index(agent) : base.control_index(agent) + 1] for agent in env.agents
            }
            _, _, terminations, truncations, infos = env.step(actions)
            agents = list(infos)
            collision = np.array([any(infos[a]["collision"] for a in agents)])
            applied = np.zeros(system.control_dim)
            control = np.zeros(system.control_dim)
            for a in agents:
                j = base.control_index(a)
                applied[j] = infos[a].get("applied_action", nominal[j])
                control[j] = infos[a]["control"]
            intervened = (
                np.array([infos[agents[0]]["filter_intervened"]]) if "filter_intervened" in infos[agents[0]] else None
            )
            change = np.array([(np.abs(applied - nominal) * half).sum()])
            margin = np.array([min(infos[a]["margin"] for a in agents)])
            one.step(collision, intervened, change, (applied * half)[None], margin)
            task.advance(base.full_state[None], control[None], sc.dt, one.active & ~collision, (k + 1) * sc.dt)
            done = collision[0] or any(terminations.values()) or any(truncations.values()) or not env.agents
            one.active &= not done
            if done:
                break
        tally.collided[i] = one.collided[0]
        tally.running_steps += one.running_steps
        tally.interventions += one.interventions
        tally.change += one.change
        tally.variation[i], tally.min_margin[i] = one.variation[0], one.min_margin[0]
        reached[i], reach_time[i] = task.reached[0], task.reach_time[0]
        env.close()
    task.reached, task.reach_time = reached, reach_time
    return tally.row(config, task, system.control_dim, threshold, time.perf_counter() - start)


def _with_interval(value: float, row: dict[str, Any]) -> str:
    """A collision rate with its 95 % Wilson interval, in percent."""
    return f"{100 * value:.2f} [{100 * row['collision_ci_low']:.2f}, {100 * row['collision_ci_high']:.2f}]"


FILTER_COLUMNS = (
    ("label", "configuration", "{}"),
    ("threshold", "threshold", "{:.3g}"),
    ("collision_rate", "collision % [95 % CI]", _with_interval),
    ("intervention_rate", "intervention %", "pct1"),
    ("mean_input_change", "mean |u - u_nom|", "{:.3f}"),
    ("total_variation", "input TV", "{:.2f}"),
    ("min_margin", "min l", "{:.3f}"),
    ("goal_rate", "goal %", "pct1"),
    ("mean_goal_time", "goal time (s)", "{:.2f}"),
    ("wall_time", "wall (s)", "{:.1f}"),
)


def filter_table(rows: Sequence[dict[str, Any]]) -> str:
    """The markdown table of :func:`evaluate_filters` rows."""
    return markdown_table(rows, FILTER_COLUMNS)


def write_filter_results(rows: Sequence[dict[str, Any]], out: str | os.PathLike, header: dict[str, Any]) -> None:
    """``out`` with suffixes .csv, .json and .md, each written atomically."""
    write_results(out, header, rows, filter_table(rows))


#: header keys that describe one invocation's filters rather than its episodes; the rows carry the
#: same facts (kind, gamma, backup_horizon, backup_disturbance, policy), so tables that differ only in these merge
PER_INVOCATION_KEYS = ("filters", "gammas", "backup_horizon", "backup_disturbance", "policy")


def _episode_header(header: dict[str, Any]) -> dict[str, Any]:
    """The keys of a table's header that fix its episodes, as they read back from the JSON file."""
    kept = {k: v for k, v in header.items() if k not in PER_INVOCATION_KEYS and k != "results"}
    return json.loads(json.dumps(kept, default=str, sort_keys=True))


def filter_table_rows(out: str | os.PathLike, header: dict[str, Any]) -> list[dict[str, Any]]:
    """The rows of the filter table already at ``out`` that a study with ``header`` may merge into
    (none if there is no table). A table of other episodes (another scene, seed, count, start rule,
    pursuer, nominal policy, ...) raises ``ValueError`` naming the first setting that differs: its
    rows were not measured on the same episodes, so they cannot share a table. ``reach filter-eval``
    calls this before any episode runs, and again under the table's lock when it writes."""
    return _stored_filter_table(out, header).get("results", [])


def _stored_filter_table(out: str | os.PathLike, header: dict[str, Any]) -> dict[str, Any]:
    """The whole table at ``out`` (header and rows; ``{}`` if there is none), checked as
    :func:`filter_table_rows` says."""
    path = Path(out).with_suffix(".json")
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        unreadable = f"{path}: existing filter results are unreadable ({err}); move the file away to start over"
        raise ValueError(unreadable) from err
    if not isinstance(data, dict) or not isinstance(data.get("results"), list):
        raise ValueError(f"{path} is not a filter results table; use another --out or delete it")
    old, new = _episode_header(data), _episode_header(header)
    for key in sorted(old.keys() | new.keys()):
        if old.get(key) != new.get(key):
            raise ValueError(
                f"{path} holds filter results for other episodes ({key}: {old.get(key)!r} there, "
                f"{new.get(key)!r} now); use another --out or delete it"
            )
    return data


def merge_filter_results(
    rows: Sequence[dict[str, Any]], out: str | os.PathLike, header: dict[str, Any]
) -> list[dict[str, Any]]:
    """Merge ``rows`` into the filter table at ``out`` and rewrite it; returns the merged rows.

    As ``reach evaluate`` does with its table: rows of configurations already there and not rerun
    are kept (a second ``reach filter-eval`` with another value function into the same ``--out``
    adds its rows instead of erasing the first's), a row with the same label replaces the old one,
    and the read-merge-write runs under a lock on ``out.lock``."""
    out = Path(out)
    with exclusive_lock(out.with_suffix(".lock"), f"filter results {out}", wait=True):
        stored = _stored_filter_table(out, header)  # one read: its rows and its header
        merged = merge_rows(stored.get("results", []), rows, key="label")
        joined = dict(header)
        for key in ("filters", "gammas"):  # the union of what the merged invocations ran
            lists = [v for v in (stored.get(key), header.get(key)) if isinstance(v, list)]
            if lists:
                joined[key] = list(dict.fromkeys(x for values in lists for x in values))
        write_filter_results(merged, out, joined)
    return merged


#: where :func:`outside_states` draws candidate starts: the system's whole domain, or the scene's own starts
START_FROM = ("domain", "scene")


def outside_states(
    value_function: ValueFunction,
    episodes: int,
    margin: float,
    seed: int,
    scene: Scene | None = None,
    max_draws_per_episode: int = 100,
) -> np.ndarray:
    """``episodes`` states of ``{V(x, T) > margin}`` (float64), seeded: uniform over the system's
    domain, or, given ``scene``, the scene's own starts (its initial-state sampler) that lie there,
    so a merge stays a merge. Too few such starts raise ``ValueError`` saying how many were found."""
    import torch

    from safety.verify import sample_superlevel_set, values_at

    horizon = value_function.system.horizon
    if scene is None:
        x, _ = sample_superlevel_set(value_function, margin, episodes, seed, horizon)
        return x.double().numpy()
    rng = np.random.default_rng(seed)
    sampler, kept, draws = scene.sampler(), [], 0
    have = 0
    while have < episodes:
        if draws >= max_draws_per_episode * episodes:
            raise ValueError(
                f"only {have} of {episodes} starts of scene {scene.name} lie in {{V > {margin:g}}} after "
                f"{draws} draws; lower --start-margin or start from the domain"
            )
        batch = np.stack([sampler.sample(scene.system, rng) for _ in range(2 * episodes)])  # the scene's API
        draws += len(batch)
        v = values_at(value_function, torch.as_tensor(batch, dtype=torch.float32), horizon).numpy()
        kept.append(batch[v > margin])
        have += int((v > margin).sum())
    return np.concatenate(kept)[:episodes]


def record_side_by_side(
    scene: str | Scene,
    value_function: ValueFunction,
    path: str,
    threshold: float | None = None,
    seeds: Sequence[int] = (0, 1, 2),
    time_to_go: float | str | None = None,
    task: GoalTask | None = None,
    scene_overrides: dict[str, Any] | None = None,
    initial_states: np.ndarray | None = None,
    kinds: Sequence[str] = ("switch",),
    gamma: float = DEFAULT_GAMMA,
    backup_horizon: float | None = None,
    backup_disturbance: str = "robust",
    policy: str | None = None,
) -> str:
    """A GIF of a few episodes from the same starts: the nominal policy (left), then the same policy
    under each filter kind in ``kinds``, side by side."""
    from reach_envs.env import ReachEnv
    from reach_envs.recording import record_panels
    from safety.wrappers import SafetyFilterWrapper

    sc = _scene(scene, scene_overrides).replace(trails=True)
    first = task if task is not None else make_task(sc.system)
    tasks = [first] + [copy.deepcopy(first) for _ in kinds]
    envs: list[Any] = [ReachEnv(sc, render_mode="rgb_array")]
    envs += [
        SafetyFilterWrapper(
            ReachEnv(sc, render_mode="rgb_array"),
            value_function,
            threshold,
            time_to_go,
            kind=k,
            gamma=gamma,
            backup_horizon=backup_horizon,
            backup_disturbance=backup_disturbance,
            policy=policy,
        )
        for k in kinds
    ]
    bases = [env.unwrapped for env in envs]

    def policy(j: int) -> Any:
        return lambda obs: tasks[j].nominal_actions(bases[j].state[None])[0].astype(np.float32)

    def reset_tasks(k: int) -> None:
        for t, base in zip(tasks, bases):
            t.reset(base.state[None], np.random.default_rng(seeds[k]))

    def caption(j: int, info: dict[str, Any] | None) -> str:
        if j == 0:
            return "nominal policy"
        name = kinds[j - 1]
        if info is None:
            return name
        return f"{name}: FILTER ACTIVE" if info["filter_intervened"] else f"{name}: nominal kept"

    options = None if initial_states is None else [{"state": initial_states[k]} for k in range(len(seeds))]
    record_panels(
        envs, path, [policy(j) for j in range(len(envs))], list(seeds), options, caption=caption, on_reset=reset_tasks
    )
    for env in envs:
        env.close()
    return path


@dataclass
class FilterStudy:
    """What ``reach filter-eval`` and the demo compute: the same episodes, nominal and filtered.

    Attributes:
        rows: one row per configuration (nominal first), as :func:`evaluate_filters` returns them.
        paths: the files written (results, trade-off plot, GIF).
    """

    rows: list[dict[str, Any]]
    paths: list[str]


def run_filter_study(
    scene: str | Scene,
    value_functions: Sequence[tuple[str, ValueFunction]],
    out: str | os.PathLike,
    thresholds: Sequence[float | None] = (None,),
    episodes: int = 1000,
    seed: int = 0,
    time_to_go: float | str | None = None,
    pursuer: str | ValueFunction | None = None,
    start_outside: ValueFunction | None = None,
    start_margin: float = 0.1,
    start_from: str = "domain",
    gif: str | os.PathLike | None = None,
    gif_threshold: float | None = None,
    pettingzoo: bool = False,
    header: dict[str, Any] | None = None,
    title: str | None = None,
    kinds: Sequence[str] = ("switch",),
    gammas: Sequence[float] = (DEFAULT_GAMMA,),
    nominal: NominalPolicy | None = None,
    backup_horizon: float | None = None,
    backup_disturbance: str = "robust",
    merge: bool = False,
    policy: str | None = None,
) -> FilterStudy:
    """The one filter-evaluation pipeline: episodes, results, trade-off plot and a side-by-side GIF.

    Args:
        value_functions: ``(label, value function)`` pairs, each filtered by every kind in ``kinds``
            at every threshold (and, for ``"smooth"``, every ``gamma`` in ``gammas``).
        pursuer: ``None`` keeps the scene's disturbance; a name (``"pursue"``, ``"random"``) replaces
            it; a value function makes the pursuer play its worst-case ``d*``.
        start_outside: draw the episodes' starts from ``{V > start_margin}`` of this value function:
            uniform over the system's domain (``start_from="domain"``) or among the scene's own
            starts (``"scene"``: the merge's starts that lie outside the learned BRT).
        gif: also record three episodes (nominal, then the first value function under each kind,
            side by side), preferring episodes in which the nominal policy crashed; ``gif_threshold``
            (default: the first threshold) is the filters' threshold there.
        backup_horizon: the lookahead's backup rollout in seconds (default: the system's horizon).
        backup_disturbance: the lookahead's predicted disturbance paths (``"robust"`` or ``"model"``).
        policy: the filters' backup input, ``"gradient"`` (``u*``), ``"greedy"``
            (:class:`~safety.value_policies.GreedyPolicy`) or ``None``: each kind's default.
        nominal: the nominal policy (float64 states ``(N, n)`` -> normalised actions ``(N, m_u)``);
            default: the scene system's goal task (:func:`~studies.tasks.make_task`), which for a
            system without goals keeps the centre of the control box.
        merge: add the rows to a table already at ``out`` (:func:`merge_filter_results`; it must
            hold the same episodes, checked before any episode runs) instead of replacing it. The
            study's rows and its trade-off plot are then the merged table's.
    """
    from studies.plots import plot_filter_tradeoff

    sc = _scene(scene, None)
    overrides: dict[str, Any] = {}
    if pursuer is not None:
        if not sc.system.disturbance_dim:
            raise ValueError(f"pursuer {pursuer!r}: scene {sc.name} has no disturbance input")
        overrides["disturbance"] = pursuer if isinstance(pursuer, str) else worst_case_disturbance(pursuer)
    if start_from not in START_FROM:
        raise ValueError(f"start_from must be one of {START_FROM}, got {start_from!r}")
    table_header = {"scene": sc.name, "episodes": episodes, "seed": seed, **(header or {})}
    if merge:
        filter_table_rows(out, table_header)  # refused before any episode runs
    starts = (
        None
        if start_outside is None
        else outside_states(start_outside, episodes, start_margin, seed, sc if start_from == "scene" else None)
    )
    task = make_task(sc.system, nominal)
    configs = [FilterConfig("nominal")]
    for label, vf in value_functions:
        for kind in kinds:
            for th in thresholds:
                for gamma in gammas if kind == "smooth" else (DEFAULT_GAMMA,):
                    configs.append(FilterConfig(label, vf, th, kind, gamma, backup_horizon, backup_disturbance, policy))
    if pettingzoo:
        if starts is not None:
            raise ValueError("the PettingZoo path samples its own starts; drop start_outside or pettingzoo")
        rows = [
            evaluate_filter_parallel(sc, c, episodes, seed, time_to_go, task=task, scene_overrides=overrides)
            for c in configs
        ]
    else:
        rows = evaluate_filters(
            sc, configs, episodes, seed, time_to_go, task=task, scene_overrides=overrides, initial_states=starts
        )
    out = Path(out)
    fresh = rows
    if merge:
        rows = merge_filter_results(rows, out, table_header)
    else:
        write_filter_results(rows, out, table_header)
    paths = [str(out.with_suffix(s)) for s in (".csv", ".json", ".md")]
    tradeoff = out.with_name(out.stem + "_tradeoff.png")
    paths.append(str(plot_filter_tradeoff(rows, tradeoff, title=title or sc.name)))
    if gif is not None and value_functions:
        picks = list(dict.fromkeys([*fresh[0]["collided_episodes"][:3], 0, 1, 2]))[:3]
        record_side_by_side(
            sc,
            value_functions[0][1],
            str(gif),
            gif_threshold if gif_threshold is not None else thresholds[0],
            [seed + i for i in picks],
            time_to_go,
            scene_overrides=overrides,
            initial_states=None if starts is None else starts[picks],
            kinds=kinds,
            gamma=gammas[0],
            backup_horizon=backup_horizon,
            backup_disturbance=backup_disturbance,
            policy=policy,
            task=task,
        )
        paths.append(str(gif))
    return FilterStudy(rows, paths)


__all__ = [
    "PER_INVOCATION_KEYS",
    "FilterConfig",
    "FilterStudy",
    "default_threshold",
    "evaluate_filter_parallel",
    "evaluate_filters",
    "filter_table_rows",
    "merge_filter_results",
    "outside_states",
    "record_side_by_side",
    "run_filter_study",
]
