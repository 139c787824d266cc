"""Episodes of a goal-seeking task with and without a safety filter, tallied into one row each.

:func:`evaluate_filters` runs ``N`` episodes of a scene in one vector environment per
configuration, every configuration from the same seeded initial states and task goals: the nominal
policy alone (``value_function=None``) and under the filter of each
:class:`~studies.filter_configs.FilterConfig`. Per configuration it reports the collision rate (95 %
Wilson interval), the intervention rate (filtered steps / running steps), the mean absolute change of
the input (physical units, per input and step), the goal-reaching rate and mean time, and the wall
time. :func:`evaluate_filter_parallel` computes the same numbers through the PettingZoo parallel
environment, episode by episode (a cross-check of the two paths). :func:`outside_states` draws starts
outside a value function's BRT.

An episode ends at its first collision (the environments' ``terminate_on_collision``), on leaving the
arena, or at the scene's horizon; the filter evaluates ``V`` at the time-to-go its settings give
(default: the value function's own horizon, a fixed-horizon filter).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from reach.value_function import ValueFunction
from reach_envs.scenes import Scene, make_scene
from reach_envs.vector import ReachVectorEnv
from safety.filters.settings import make_filter_settings
from safety.filters.wrappers import SafetyFilterParallelWrapper, SafetyFilterVectorWrapper
from safety.verification.metrics import wilson_interval
from safety.verification.verify import sample_superlevel_set, values_at
from studies.filter_configs import FilterConfig
from studies.filter_tables import labelled, settings_columns
from studies.goal_tasks import GoalTask, make_task


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
        """The configuration's row of metrics (labelled: :func:`~studies.filter_tables.labelled`)."""
        n = len(self.collided)
        hits = int(self.collided.sum())
        low, high = wilson_interval(hits, n)
        reached = task.reached & ~self.collided
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
            **settings_columns(config),
            "goal_rate": float(reached.mean()) if task.has_goal else float("nan"),
            "mean_goal_time": float(np.nanmean(task.reach_time[reached])) if reached.any() else float("nan"),
            "wall_time": wall,
            "collided_episodes": [int(i) for i in np.flatnonzero(self.collided)[:20]],
        }
        return labelled(row)


def _scene(scene: str | Scene, overrides: dict[str, Any] | None) -> Scene:
    return make_scene(scene, **(overrides or {}))


def _filtered(wrapper: Any, base: Any, config: FilterConfig, time_to_go: float | str | None) -> Any:
    """``base`` under ``config``'s filter (``time_to_go``, if given, replacing its settings' own)."""
    return wrapper(base, config.value_function, settings=make_filter_settings(config.settings, time_to_go=time_to_go))


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
    ``time_to_go`` (not ``None``) replaces every configuration's own (its settings').
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
            env = _filtered(SafetyFilterVectorWrapper, base, config, time_to_go)
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
    from reach_envs.parallel import MultiVehicleParallelEnv  # lazy: the parallel env only for the cross-check

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
            env = _filtered(SafetyFilterParallelWrapper, base, config, time_to_go)
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


def outside_states(
    value_function: ValueFunction,
    episodes: int,
    margin: float,
    seed: int,
    scene: Scene | None = None,
    max_draws_per_episode: int = 100,
) -> np.ndarray:
    """``episodes`` states of ``{V(x, T) > margin}`` (float64; ``{V(x, T) < -margin}``, where the task
    is feasible, for a reach kind: ``V`` oriented by the kind), seeded: uniform over the system's
    domain, or, given ``scene``, the scene's own starts (its initial-state sampler) that lie there,
    so a merge stays a merge. Too few such starts raise ``ValueError`` saying how many were found."""
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
        v = value_function.system.problem.orient(
            values_at(value_function, torch.as_tensor(batch, dtype=torch.float32), horizon)
        ).numpy()
        kept.append(batch[v > margin])
        have += int((v > margin).sum())
    return np.concatenate(kept)[:episodes]


__all__ = ["evaluate_filter_parallel", "evaluate_filters", "outside_states"]
