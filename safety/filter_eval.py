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
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from reach.value_function import ValueFunction
from reach_envs.scenes import Scene, make_scene
from reach_envs.vector import ReachVectorEnv
from safety.metrics import wilson_interval
from safety.results_io import write_results
from safety.tasks import GoalTask, make_task
from safety.wrappers import SafetyFilterParallelWrapper, SafetyFilterVectorWrapper, default_threshold


@dataclass
class FilterConfig:
    """One configuration: a label, a value function (``None``: nominal policy alone), a threshold."""

    label: str
    value_function: ValueFunction | None = None
    threshold: float | None = None


class _Tally:
    """Per-configuration counters over running episodes."""

    def __init__(self, n: int) -> None:
        self.collided = np.zeros(n, dtype=bool)
        self.active = np.ones(n, dtype=bool)
        self.running_steps = 0
        self.interventions = 0
        self.change = 0.0

    def step(self, collision: np.ndarray, intervened: np.ndarray | None, change: np.ndarray) -> None:
        a = self.active
        self.collided |= collision & a
        self.running_steps += int(a.sum())
        if intervened is not None:
            self.interventions += int((intervened & a).sum())
        self.change += float(change[a].sum())

    def row(self, config: FilterConfig, task: GoalTask, inputs: int, threshold: float | None, wall: float) -> dict:
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
            "goal_rate": float(reached.mean()),
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
            env = SafetyFilterVectorWrapper(base, config.value_function, config.threshold, time_to_go)
            threshold = env.safety_filter.threshold
        options = None if initial_states is None else {"state": initial_states}
        env.reset(seed=seed, options=options)
        task.reset(base.state, np.random.default_rng(seed))
        tally = _Tally(episodes)
        for k in range(sc.max_steps):
            nominal = task.nominal_actions(base.state).astype(np.float32)
            _, _, terminated, truncated, info = env.step(nominal)
            applied = info.get("applied_action", nominal)
            change = (np.abs(np.asarray(applied, dtype=np.float64) - nominal) * half).sum(axis=1)
            tally.step(info["collision"], info.get("filter_intervened"), change)
            task.advance(base.state, info["control"], sc.dt, tally.active & ~info["collision"], (k + 1) * sc.dt)
            tally.active &= ~(terminated | truncated)
            if not tally.active.any():
                break
        env.close()
        rows.append(tally.row(config, task, system.control_dim, threshold, time.perf_counter() - start))
    return rows


def _labelled(row: dict[str, Any]) -> dict[str, Any]:
    """``value_function`` = the configuration's name; ``label`` adds the threshold when filtered."""
    name = row["label"]
    threshold = row["threshold"]
    return {**row, "value_function": name, "label": name if threshold is None else f"{name} @ {threshold:.3g}"}


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
            env = SafetyFilterParallelWrapper(base, config.value_function, config.threshold, time_to_go)
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
            one.step(collision, intervened, change)
            task.advance(base.full_state[None], control[None], sc.dt, one.active & ~collision, (k + 1) * sc.dt)
            done = collision[0] or any(terminations.values()) or any(truncations.values()) or not env.agents
            one.active &= not done
            if done:
                break
        tally.collided[i] = one.collided[0]
        tally.running_steps += one.running_steps
        tally.interventions += one.interventions
        tally.change += one.change
        reached[i], reach_time[i] = task.reached[0], task.reach_time[0]
        env.close()
    task.reached, task.reach_time = reached, reach_time
    return tally.row(config, task, system.control_dim, threshold, time.perf_counter() - start)


FILTER_COLUMNS = (
    ("label", "configuration", "{}"),
    ("threshold", "threshold", "{:.3g}"),
    ("collision_rate", "collision % [95 % CI]", "ci"),
    ("intervention_rate", "intervention %", "pct"),
    ("mean_input_change", "mean |u - u_nom|", "{:.3f}"),
    ("goal_rate", "goal %", "pct"),
    ("mean_goal_time", "goal time (s)", "{:.2f}"),
    ("wall_time", "wall (s)", "{:.1f}"),
)


def filter_table(rows: Sequence[dict[str, Any]]) -> str:
    """The markdown table of :func:`evaluate_filters` rows."""
    lines = ["| " + " | ".join(h for _, h, _ in FILTER_COLUMNS) + " |", "|" + "---|" * len(FILTER_COLUMNS)]
    for r in rows:
        cells = []
        for key, _, spec in FILTER_COLUMNS:
            v = r.get(key)
            if v is None or (isinstance(v, float) and math.isnan(v)):
                cells.append("-")
            elif spec == "ci":
                cells.append(f"{100 * v:.2f} [{100 * r['collision_ci_low']:.2f}, {100 * r['collision_ci_high']:.2f}]")
            elif spec == "pct":
                cells.append(f"{100 * v:.1f}")
            else:
                cells.append(spec.format(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_filter_results(rows: Sequence[dict[str, Any]], out: str | os.PathLike, header: dict[str, Any]) -> None:
    """``out`` with suffixes .csv, .json and .md, each written atomically."""
    write_results(out, header, rows, filter_table(rows))


def worst_case_disturbance(value_function: ValueFunction, time_to_go: float | None = None) -> Any:
    """A scene disturbance ``state -> d*`` that attacks with the value function's optimal disturbance."""
    import torch

    from safety.policy import OptimalPolicy

    policy = OptimalPolicy(value_function)
    t = value_function.system.horizon if time_to_go is None else float(time_to_go)

    def attack(x: np.ndarray) -> np.ndarray:
        return policy.disturbance(torch.as_tensor(x, dtype=torch.float64), t).numpy()

    return attack


def outside_states(value_function: ValueFunction, episodes: int, margin: float, seed: int) -> np.ndarray:
    """``episodes`` states drawn uniformly from ``{V(x, T) > margin}`` (float64), seeded."""
    from safety.verify import sample_superlevel_set

    x, _ = sample_superlevel_set(value_function, margin, episodes, seed, value_function.system.horizon)
    return x.double().numpy()


def _label(frame: np.ndarray, text: str) -> np.ndarray:
    """``frame`` with a header strip carrying ``text`` (red when the filter is active)."""
    from PIL import Image, ImageDraw

    strip = Image.new("RGB", (frame.shape[1], 22), "white")
    ImageDraw.Draw(strip).text((8, 5), text, fill=(200, 0, 0) if "ACTIVE" in text else (0, 0, 0))
    return np.concatenate([np.asarray(strip), frame[..., :3]], axis=0)


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
) -> str:
    """A GIF of a few episodes, nominal policy (left) and filtered (right), from the same starts."""
    from reach_envs.env import ReachEnv
    from reach_envs.recording import save_gif
    from safety.wrappers import SafetyFilterWrapper

    sc = _scene(scene, scene_overrides).replace(trails=True)
    task_l = task if task is not None else make_task(sc.system)
    task_r = copy.deepcopy(task_l)
    frames = []
    for k, seed in enumerate(seeds):
        left = ReachEnv(sc, render_mode="rgb_array")
        right = SafetyFilterWrapper(ReachEnv(sc, render_mode="rgb_array"), value_function, threshold, time_to_go)
        options = None if initial_states is None else {"state": initial_states[k]}
        envs = [(left, task_l, left), (right, task_r, right.unwrapped)]
        done = [False, False]
        last = [None, None]
        status = "filtered"
        for e, t, base in envs:
            e.reset(seed=seed, options=options)
            t.reset(base.state[None], np.random.default_rng(seed))
        for step in range(sc.max_steps + 1):
            pics = []
            for j, (e, _, _) in enumerate(envs):
                if not done[j]:
                    last[j] = e.render()
                pics.append(last[j])
            frames.append(np.concatenate([_label(pics[0], "nominal policy"), _label(pics[1], status)], axis=1))
            if all(done) or step == sc.max_steps:
                break
            for j, (e, t, base) in enumerate(envs):
                if done[j]:
                    continue
                action = t.nominal_actions(base.state[None])[0].astype(np.float32)
                _, _, term, trunc, info = e.step(action)
                done[j] = term or trunc
                if j == 1:
                    status = "filtered: FILTER ACTIVE" if info["filter_intervened"] else "filtered: nominal kept"
        left.close()
        right.close()
    save_gif(frames, path, fps=max(1, round(1.0 / sc.dt)))
    return path


__all__ = [
    "FilterConfig",
    "default_threshold",
    "evaluate_filter_parallel",
    "evaluate_filters",
    "outside_states",
    "record_side_by_side",
    "worst_case_disturbance",
]
