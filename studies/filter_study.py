"""The one filter-evaluation pipeline: episodes, results table, trade-off plot, side-by-side GIF.

Why: ``reach filter-eval`` and the demo run the same study, so it lives once, here.
:func:`run_filter_study` takes its set-up as one :class:`~studies.filter_configs.FilterStudySettings`
(episodes, filters, outputs) or as the flat keywords it always took; it draws the starts, runs every
configuration on the same episodes (:mod:`studies.filter_episodes`), writes or merges the table
(:mod:`studies.filter_tables`), plots the trade-off and records a few episodes side by side
(:func:`record_side_by_side`).
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from reach.validation import check_seed
from reach.value_function import ValueFunction
from reach_envs.scenes import Scene, make_scene
from safety.filters.settings import FilterSettings, make_filter_settings
from safety.filters.wrappers import SafetyFilterWrapper
from safety.value_policies import worst_case_disturbance
from studies.filter_configs import EpisodeSettings, FilterStudySettings
from studies.filter_episodes import evaluate_filter_parallel, evaluate_filters, outside_states
from studies.filter_tables import filter_table_rows, merge_filter_results, write_filter_results
from studies.goal_tasks import GoalTask, make_task


@dataclass(frozen=True, eq=False)  # eq=False: an array of starts has no single truth value
class RecordedEpisodes:
    """Which episodes :func:`record_side_by_side` shows, and who else acts in them.

    Attributes:
        seeds: one episode per seed (at least one).
        initial_states: one start state per seed (``None``: the scene's own sampler).
        task: the nominal policy's task (default: the scene system's goal task).
        scene_overrides: keyword overrides of the scene (e.g. ``disturbance=`` for a pursuer).
    """

    seeds: Sequence[int] = (0, 1, 2)
    initial_states: np.ndarray | None = None
    task: GoalTask | None = None
    scene_overrides: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "seeds", tuple(check_seed("seed", s) for s in self.seeds))
        if not self.seeds:
            raise ValueError("RecordedEpisodes needs at least one seed")
        if self.initial_states is not None and len(self.initial_states) < len(self.seeds):
            raise ValueError(
                f"initial_states holds {len(self.initial_states)} starts for {len(self.seeds)} seeds {self.seeds}"
            )


def record_side_by_side(
    scene: str | Scene,
    value_function: ValueFunction,
    path: str,
    threshold: float | None = None,
    episodes: RecordedEpisodes | None = None,
    *,
    kinds: Sequence[str] = (FilterSettings.kind,),
    settings: FilterSettings | None = None,
    **options: Any,
) -> str:
    """A GIF of a few episodes from the same starts: the nominal policy (left), then the same policy
    under each filter kind in ``kinds``, side by side. ``episodes`` (:class:`RecordedEpisodes`,
    default: seeds 0, 1, 2 from the scene's starts) picks the episodes. The filters share
    ``settings``, with ``threshold`` and any other :class:`FilterSettings` field given by keyword
    (``time_to_go=``, ``gamma=``, ``backup_horizon=``, ``policy=``, ...) replacing its own; each has
    its own kind."""
    # lazy: the env and recording only when a GIF is recorded
    from reach_envs.env import ReachEnv
    from reach_envs.recording import record_panels

    shared = make_filter_settings(settings, threshold=threshold, **options)
    picked = episodes if episodes is not None else RecordedEpisodes()
    seeds, task, initial_states = picked.seeds, picked.task, picked.initial_states
    sc = make_scene(scene, **(picked.scene_overrides or {})).replace(trails=True)
    first = task if task is not None else make_task(sc.system)
    tasks = [first] + [copy.deepcopy(first) for _ in kinds]
    envs: list[Any] = [ReachEnv(sc, render_mode="rgb_array")]
    envs += [
        SafetyFilterWrapper(
            ReachEnv(sc, render_mode="rgb_array"), value_function, settings=make_filter_settings(shared, kind=k)
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

    starts = None if initial_states is None else [{"state": initial_states[k]} for k in range(len(seeds))]
    record_panels(
        envs, path, [policy(j) for j in range(len(envs))], list(seeds), starts, caption=caption, on_reset=reset_tasks
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


def _pursuer_overrides(scene: Scene, pursuer: str | ValueFunction | None) -> dict[str, Any]:
    """The scene overrides that put ``pursuer`` in charge of the disturbance (none for ``None``)."""
    if pursuer is None:
        return {}
    if not scene.system.disturbance_dim:
        raise ValueError(f"pursuer {pursuer!r}: scene {scene.name} has no disturbance input")
    return {"disturbance": pursuer if isinstance(pursuer, str) else worst_case_disturbance(pursuer)}


def _starts(scene: Scene, episodes: EpisodeSettings) -> np.ndarray | None:
    """The episodes' starts: ``None`` (the scene's sampler), or states outside ``start_outside``'s BRT."""
    if episodes.start_outside is None:
        return None
    source = scene if episodes.start_from == "scene" else None
    return outside_states(episodes.start_outside, episodes.episodes, episodes.start_margin, episodes.seed, source)


def run_filter_study(
    scene: str | Scene,
    value_functions: Sequence[tuple[str, ValueFunction]],
    out: str | os.PathLike,
    settings: FilterStudySettings | None = None,
    **options: Any,
) -> FilterStudy:
    """The one filter-evaluation pipeline: episodes, results, trade-off plot and a side-by-side GIF.

    Args:
        value_functions: ``(label, value function)`` pairs, each filtered by every filter of the
            grid (:class:`~studies.filter_configs.FilterGrid`: every kind at every threshold and,
            for ``"smooth"``, every gamma).
        out: the results path (``.csv``, ``.json`` and ``.md`` are written, and ``*_tradeoff.png``).
        settings: the study's :class:`~studies.filter_configs.FilterStudySettings`: its episodes
            (count, seed, pursuer, starts, nominal policy, PettingZoo path), its filters and its
            outputs (GIF, header, title, merge).
        **options: the same set-up as flat keywords, each replacing its field of ``settings``:
            ``thresholds``, ``kinds``, ``gammas``, ``episodes``, ``seed``, ``pursuer``,
            ``start_outside``, ``start_margin``, ``start_from``, ``nominal``, ``pettingzoo``,
            ``gif``, ``gif_threshold``, ``header``, ``title``, ``merge``, and the filters' shared
            :class:`~safety.filters.settings.FilterSettings` fields (``time_to_go``,
            ``backup_horizon``, ``backup_disturbance``, ``policy``).

    With ``gif``, three episodes are recorded (nominal, then the first value function under each
    kind), preferring episodes in which the nominal policy crashed. With ``merge``, rows join a table
    of the same episodes already at ``out`` (checked before any episode runs); the study's rows and
    its trade-off plot are then the merged table's.
    """
    from studies.plots import plot_filter_tradeoff  # lazy: the plotting module only when a study runs

    study = FilterStudySettings.from_options(settings, **options)
    episodes, grid, output = study.episodes, study.filters, study.output
    sc = make_scene(scene)
    overrides = _pursuer_overrides(sc, episodes.pursuer)
    table_header = {"scene": sc.name, "episodes": episodes.episodes, "seed": episodes.seed, **(output.header or {})}
    if output.merge:
        filter_table_rows(out, table_header)  # refused before any episode runs
    starts = _starts(sc, episodes)
    task = make_task(sc.system, episodes.nominal)
    configs = grid.configs(value_functions)
    if episodes.pettingzoo:
        if starts is not None:
            raise ValueError("the PettingZoo path samples its own starts; drop start_outside or pettingzoo")
        rows = [
            evaluate_filter_parallel(sc, c, episodes.episodes, episodes.seed, task=task, scene_overrides=overrides)
            for c in configs
        ]
    else:
        rows = evaluate_filters(
            sc, configs, episodes.episodes, episodes.seed, task=task, scene_overrides=overrides, initial_states=starts
        )
    out = Path(out)
    fresh = rows
    if output.merge:
        rows = merge_filter_results(rows, out, table_header)
    else:
        write_filter_results(rows, out, table_header)
    paths = [str(out.with_suffix(s)) for s in (".csv", ".json", ".md")]
    tradeoff = out.with_name(out.stem + "_tradeoff.png")
    paths.append(str(plot_filter_tradeoff(rows, tradeoff, title=output.title or sc.name)))
    if output.gif is not None and value_functions:
        picks = list(dict.fromkeys([*fresh[0]["collided_episodes"][:3], 0, 1, 2]))[:3]
        record_side_by_side(
            sc,
            value_functions[0][1],
            str(output.gif),
            output.gif_threshold if output.gif_threshold is not None else grid.thresholds[0],
            RecordedEpisodes(
                seeds=[episodes.seed + i for i in picks],
                initial_states=None if starts is None else starts[picks],
                task=task,
                scene_overrides=overrides,
            ),
            kinds=grid.kinds,
            settings=make_filter_settings(grid.shared, gamma=grid.gammas[0]),
        )
        paths.append(str(output.gif))
    return FilterStudy(rows, paths)


__all__ = ["FilterStudy", "RecordedEpisodes", "record_side_by_side", "run_filter_study"]
