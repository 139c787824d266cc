"""The fleet study: collisions, goals and decision time of fleet filters against the fleet's size.

:func:`run_fleet_eval` rolls out ``episodes`` episodes of every fleet scene (:mod:`reach_envs.fleet_scenes`)
at every size and under every method, the nominal input of every car steering it to its goal
(:func:`reach_envs.fleet.goal_seeking`). The episodes of one cell run as one batch, the filter
deciding for every episode at once. Methods (:data:`METHODS`):

- ``"none"``: the nominal input, unfiltered;
- ``"fleet"``: the fleet filter composed from pairs (:class:`safety.fleet.FleetFilter`);
- ``"cbf"``: the distance CBF-QP, ``h = |p_i - p_j|^2 - R^2``, same solver (:class:`safety.fleet.DistanceCBF`);
- ``"union"``: the switch filter on the union of pairwise values (:class:`safety.fleet.NaiveUnionSwitch`).

Each row (one layout, size and method) holds the collision rate (episodes with any collision) with
its 95 % Wilson interval and the scenario bound on the collision probability at confidence
``1 - beta`` (:func:`~safety.verification.metrics.scenario_epsilon`: every episode an independent draw
of the scene's initial states), the goal rate (share of cars that reach their goal) with its
interval and its ratio to the unfiltered goal rate, the mean arrival time, the intervention rate
(share of present car-decisions the filter changed), the infeasible share (conflicts decided by
the fallback rule, of all conflicts), and the decision time per tick of one fleet (batch 1, one
thread: :func:`decision_times`).

Resumable and one owner at a time: every finished cell is merged into ``OUT.json`` (with ``.csv``
and ``.md``) atomically under ``OUT.lock``; a rerun skips the cells stored with the same settings.

The first collided episodes of each cell (``keep_collisions``, 10 by default) are also written, one
file each, to the folder ``OUT.collisions`` beside the results (:func:`collisions_folder`): each
episode's start, goals and the inputs it was given, which replay it alone exactly where re-running
the episode would not (:mod:`studies.fleet_collisions`; ``reach fleet-replay`` draws it).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from reach.json_files import read_json
from reach.locking import exclusive_lock
from reach_envs.fleet import FleetSimulator, goal_seeking, rollout
from reach_envs.fleet_scenes import FleetScene
from safety.fleet import FleetFilterSettings
from safety.verification.metrics import scenario_epsilon, wilson_interval
from studies.fleet_collisions import InputRecorder, save_collided
from studies.fleet_methods import make_method
from studies.fleet_settings import FleetEvalSettings
from studies.tables import columns_table, merge_rows, write_results

__all__ = ["collisions_folder", "decision_times", "filter_options", "run_cell", "run_fleet_eval"]


@dataclass
class _Tally:
    """What one batch of episodes of one cell adds up to."""

    episodes: int = 0
    collided: int = 0
    cars: int = 0
    arrived: int = 0
    arrival_time: float = 0.0
    decisions: int = 0
    interventions: int = 0
    conflicts: int = 0
    infeasible: int = 0
    ticks: int = 0


def _rollout(
    scene: FleetScene, decide: Callable | None, episodes: int, seed: int, tally: _Tally, keep: _Keep | None = None
) -> None:
    """``episodes`` episodes of ``scene`` at once (:func:`reach_envs.fleet.rollout`), each car's input
    decided by ``decide`` from the nominal one (``None``: the nominal input), added to ``tally``;
    with ``keep``, its collided episodes, up to the room it has left, are written to its folder
    (:func:`studies.fleet_collisions.save_collided`)."""

    def controller(x: torch.Tensor, goals: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        u = goal_seeking(x, goals, scene)
        if decide is not None:
            u, info = decide(x, u, present)
            tally.interventions += int((info.intervened & present).sum())
            tally.conflicts += int(info.conflicts.sum())
            tally.infeasible += int(info.infeasible.sum())
        tally.decisions += int(present.sum())
        tally.ticks += 1
        return u

    x0, goals = scene.sample(episodes, np.random.default_rng(seed))
    recorder = InputRecorder(controller) if keep is not None and keep.room > 0 else None
    outcome = rollout(scene, x0, goals, recorder or controller)
    if recorder is not None and keep is not None:
        chosen = outcome.any_collision & (torch.cumsum(outcome.any_collision.long(), 0) <= keep.room)
        meta = {**keep.meta, "seed": seed, "batch_episodes": episodes}
        keep.room -= len(save_collided(scene, (x0, goals), recorder, chosen, keep.folder, meta))
    tally.episodes += episodes
    tally.collided += int(outcome.any_collision.sum())
    tally.cars += episodes * scene.n_cars
    arrived = outcome.arrived
    tally.arrived += int(arrived.sum())
    tally.arrival_time += float(outcome.arrival_time[arrived].sum())


@dataclass
class _Keep:
    """Where a cell's collided episodes go, what their files record of the run, and how many more
    the cell keeps."""

    folder: Path
    meta: dict[str, Any]
    room: int


def filter_options(settings: FleetEvalSettings) -> dict[str, Any]:
    """The fleet filter's ``hold``, ``reaction_time`` and ``tie_break`` that ``settings`` runs: its own
    where given, else :class:`~safety.fleet.FleetFilterSettings`' defaults (the values the results record)."""
    given = {"hold": settings.hold, "reaction_time": settings.reaction_time, "tie_break": settings.tie_break}
    return {name: getattr(FleetFilterSettings, name) if value is None else value for name, value in given.items()}


def run_cell(
    settings: FleetEvalSettings, layout: str, n_cars: int, method: str, collisions: str | Path | None = None
) -> dict[str, Any]:
    """One row of the study: ``settings.episodes`` episodes of ``layout`` with ``n_cars`` cars under
    ``method`` (the module docstring lists its columns). With ``collisions`` (a folder), the first
    ``settings.keep_collisions`` episodes with a collision are also written there, to replay alone
    (:mod:`studies.fleet_collisions`)."""
    scene = FleetScene(layout=layout, n_cars=n_cars, density=settings.density)
    options = filter_options(settings)
    decide = make_method(method, scene, **options)
    keep = None
    if collisions is not None and settings.keep_collisions:
        meta = {"method": method, "batch": settings.batch, "study_seed": settings.seed}
        meta.update(options if method == "fleet" else {})
        keep = _Keep(Path(collisions), meta, settings.keep_collisions)
    tally = _Tally()
    start = time.perf_counter()
    batches = range(0, settings.episodes, settings.batch)
    for b, first in enumerate(batches):
        size = min(settings.batch, settings.episodes - first)
        _rollout(scene, decide, size, settings.seed + 1000 * b, tally, keep)
    wall = time.perf_counter() - start
    row = _row(settings, tally)
    row.update(layout=layout, n_cars=n_cars, method=method, key=f"{layout}/{n_cars}/{method}", wall_s=wall)
    if settings.timing_ticks and decide is not None:
        row.update(decision_times(scene, decide, settings.timing_ticks, settings.seed))
    return row


def _row(settings: FleetEvalSettings, t: _Tally) -> dict[str, Any]:
    lo, hi = wilson_interval(t.collided, t.episodes)
    g_lo, g_hi = wilson_interval(t.arrived, t.cars)
    eps = scenario_epsilon(t.collided, t.episodes, settings.beta) if t.collided < t.episodes else 1.0
    return {
        "episodes": t.episodes,
        "collisions": t.collided,
        "collision_rate": t.collided / t.episodes,
        "collision_low": lo,
        "collision_high": hi,
        "collision_bound": eps,
        "beta": settings.beta,
        "goal_rate": t.arrived / t.cars,
        "goal_low": g_lo,
        "goal_high": g_hi,
        "arrival_time": t.arrival_time / t.arrived if t.arrived else math.nan,
        "intervention_rate": t.interventions / t.decisions if t.decisions else 0.0,
        "conflicts": t.conflicts,
        "infeasible_share": t.infeasible / t.conflicts if t.conflicts else 0.0,
        "ticks": t.ticks,
    }


def decision_times(scene: FleetScene, decide: Callable, ticks: int, seed: int) -> dict[str, float]:
    """Milliseconds per decision for one fleet (batch 1) on one torch thread: median, 99th percentile
    and maximum over the first ``ticks`` decisions along an episode of ``scene`` (all of them, where
    it ends sooner: ``timed`` says how many), the nominal input filtered and applied. Conflicts form
    as the cars meet, so a count that covers the whole episode times them too."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        sim = FleetSimulator(scene)
        x, goals = scene.sample(1, np.random.default_rng(seed))
        present = torch.ones(1, scene.n_cars, dtype=torch.bool)
        times = []
        for _ in range(min(ticks, scene.max_steps)):  # an episode ends at its horizon
            if not bool(present.any()):
                break
            u = goal_seeking(x, goals, scene)
            start = time.perf_counter()
            u, _ = decide(x, u, present)
            times.append(time.perf_counter() - start)
            x, _, _, present = sim.step(x, u, present, goals)
    finally:
        torch.set_num_threads(threads)
    if not times:
        return {"decision_ms": math.nan, "decision_p99_ms": math.nan, "decision_max_ms": math.nan, "timed": 0}
    ms = np.asarray(times) * 1e3
    return {
        "decision_ms": float(np.median(ms)),
        "decision_p99_ms": float(np.percentile(ms, 99)),
        "decision_max_ms": float(ms.max()),
        "timed": len(times),
    }


def _collisions(value: float, row: dict[str, Any]) -> str:
    return f"{row['collisions']}/{row['episodes']} [{row['collision_low']:.3f}, {row['collision_high']:.3f}]"


def _goals(value: float, row: dict[str, Any]) -> str:
    return f"{value:.3f} [{row['goal_low']:.3f}, {row['goal_high']:.3f}]"


#: (key, header, format) of the study's markdown table
COLUMNS = (
    ("layout", "scene", "{}"),
    ("n_cars", "N", "{}"),
    ("method", "method", "{}"),
    ("collision_rate", "collisions (95 % CI)", _collisions),
    ("collision_bound", "eps at 1 - beta", "{:.2e}"),
    ("goal_rate", "goal rate (95 % CI)", _goals),
    ("arrival_time", "arrival s", "{:.1f}"),
    ("intervention_rate", "interventions", "{:.3f}"),
    ("infeasible_share", "infeasible", "{:.3f}"),
    ("decision_ms", "ms / decision", "{:.2f}"),
    ("decision_p99_ms", "p99 ms", "{:.1f}"),
)


def run_fleet_eval(
    settings: FleetEvalSettings, out: str | Path, progress: Callable[[str], None] | None = None
) -> list[dict[str, Any]]:
    """Every cell of ``settings`` not yet in ``OUT.json`` with the same settings, each merged in as it
    finishes; returns every stored row."""
    # OUT is a stem: "runs/density_0.2" writes runs/density_0.2.json (with_suffix would eat ".2")
    out = Path(out)
    out = out.with_name(out.name + ".json")
    # what the rows depend on: not the cells asked for, nor how many collided episodes are kept
    unrecorded = ("layouts", "sizes", "methods", "keep_collisions")
    stored_settings = {k: v for k, v in asdict(settings).items() if k not in unrecorded}
    header = {"settings": {**stored_settings, **filter_options(settings)}}  # what ran, default or not
    cells = [(lay, n, m) for lay in settings.layouts for n in settings.sizes for m in settings.methods]
    for layout, n, method in cells:
        key = f"{layout}/{n}/{method}"
        with exclusive_lock(out.with_suffix(".lock"), f"fleet results {out}", wait=True):
            stored = _stored(out, header)
        if any(r["key"] == key for r in stored):
            continue
        if progress is not None:
            progress(key)
        row = run_cell(settings, layout, n, method, collisions=collisions_folder(out))
        with exclusive_lock(out.with_suffix(".lock"), f"fleet results {out}", wait=True):
            rows = merge_rows(_stored(out, header), [row], "key")
            write_results(out, header, rows, columns_table(rows, COLUMNS))
    with exclusive_lock(out.with_suffix(".lock"), f"fleet results {out}", wait=True):
        return _stored(out, header)


def collisions_folder(results: str | Path) -> Path:
    """The folder beside a study's results file (``OUT.json``, or its stem) that holds the collided
    episodes: ``OUT.collisions``."""
    path = Path(results)
    stem = path.name[: -len(".json")] if path.name.endswith(".json") else path.name
    return path.with_name(stem + ".collisions")


def _stored(out: Path, header: dict[str, Any]) -> list[dict[str, Any]]:
    """The rows stored in ``OUT.json``; a file of other settings is refused, naming both."""
    path = out
    if not path.exists():
        return []
    data = read_json(path, "fleet results")
    if data.get("settings") != header["settings"]:
        raise ValueError(
            f"{path} holds a study with settings {data.get('settings')}, not {header['settings']}: "
            "write to another file, or delete it"
        )
    return list(data.get("results", []))
