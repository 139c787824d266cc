"""The fleet study's collided episodes, kept one file each so that any of them replays on its own.

Why: the study decides a whole batch of episodes at once, and the conflicts of every episode share
one interior-point solve (:mod:`safety.fleet.qp`), whose iterates depend on every block. An episode
re-run alone therefore meets inputs that differ from the batch's in the last digits, and over a
thousand steps of converging cars the two runs part: a collision of the study cannot be found again
by re-running its episode. What replays exactly is the episode's own inputs. The simulator's
arithmetic is elementwise per episode (:class:`reach_envs.fleet.FleetSimulator`), so the start,
the goals and the turn rates each car was given reproduce the batch's states bit for bit.

:class:`InputRecorder` keeps every tick's applied inputs of a batch (a controller wrapper);
:func:`save_collided` re-simulates each collided episode alone from them, checks that it collides
where the batch's did, and writes ``.npz`` files (arrays only, read back without pickle) holding
the scene, the settings that ran, the start, the goals, the inputs, every state and presence mask,
and which cars collided. :func:`load_episode` reads one back, refusing anything malformed, and
:func:`first_collision` says when, which cars and how close; ``reach fleet-replay`` prints that and
draws the seconds before it as a GIF. :func:`conflict_trace` reads the fleet filter's view of the
seconds before it: the colliding pair's value and the group of cars its active pairs join.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from reach.atomic import atomic_path
from reach_envs.fleet import Controller, positions, rollout
from reach_envs.fleet_scenes import FleetScene
from safety.fleet import FleetFilter, FleetFilterSettings
from safety.fleet.graph import components
from studies.fleet_methods import fleet_value

__all__ = ["FleetEpisode", "InputRecorder", "conflict_trace", "first_collision", "load_episode", "save_collided"]

#: the arrays every episode file holds
ARRAYS = ("x0", "goals", "inputs", "states", "present", "collided")


class InputRecorder:
    """Wraps a fleet controller and keeps the turn rates it returns, tick by tick (``(B, N)`` each)."""

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        self.inputs: list[torch.Tensor] = []

    def __call__(self, x: torch.Tensor, goals: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        u = self.controller(x, goals, present)
        self.inputs.append(u.detach().to(torch.float64).clone())
        return u

    def episode(self, index: int) -> torch.Tensor:
        """``(T, N)`` the inputs episode ``index`` of the batch was given."""
        return torch.stack([u[index] for u in self.inputs])


@dataclass(frozen=True)
class FleetEpisode:
    """One episode replayed alone: ``scene`` and ``meta`` (the study's settings, the batch's seed and
    the episode's index in it), ``x0`` ``(3N,)``, ``goals`` ``(N, 2)``, ``inputs`` ``(T, N)``,
    ``states`` ``(T + 1, 3N)``, ``present`` ``(T + 1, N)`` and ``collided`` ``(N,)``."""

    scene: FleetScene
    meta: dict[str, Any]
    x0: np.ndarray
    goals: np.ndarray
    inputs: np.ndarray
    states: np.ndarray
    present: np.ndarray
    collided: np.ndarray


def replay(scene: FleetScene, x0: torch.Tensor, goals: torch.Tensor, inputs: torch.Tensor) -> Any:
    """The episode from ``x0`` ``(3N,)`` to ``goals`` ``(N, 2)`` driven by ``inputs`` ``(T, N)``, alone
    (batch 1) and recorded (:func:`reach_envs.fleet.rollout`); it ends where the inputs do, at the
    latest."""
    ticks = iter(inputs)

    def controller(x: torch.Tensor, goals: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        u = next(ticks, None)
        if u is None:
            raise ValueError(f"replay: the episode outlasts its {inputs.shape[0]} recorded inputs")
        return u[None]

    return rollout(scene, x0[None], goals[None], controller, record=True)


def save_collided(
    scene: FleetScene,
    start: tuple[torch.Tensor, torch.Tensor],
    recorder: InputRecorder,
    collided: torch.Tensor,
    folder: str | os.PathLike,
    meta: dict[str, Any],
) -> list[Path]:
    """Each episode of the batch with a collision (``collided`` ``(B,)`` bool), replayed alone from its
    ``start = (x0 (B, 3N), goals (B, N, 2))`` and the inputs ``recorder`` kept, written atomically to
    ``folder/<layout>-<N>-<method>-seed<seed>-ep<index>.npz``. ``meta`` (JSON-able: the study's
    settings, the method and the batch's seed) is stored with it. A replay that does not collide as
    the batch's episode did raises: the file would not show what happened."""
    x0, goals = start
    written = []
    for index in torch.nonzero(collided).flatten().tolist():
        inputs = recorder.episode(index)
        out = replay(scene, x0[index], goals[index], inputs)
        if not bool(out.any_collision[0]):
            raise RuntimeError(f"episode {index} of the batch (seed {meta.get('seed')}) did not collide when replayed")
        info = {**meta, "index": index, "scene": _scene_fields(scene)}
        name = f"{scene.layout}-{scene.n_cars}-{meta.get('method', 'fleet')}-seed{meta.get('seed')}-ep{index}.npz"
        path = Path(folder) / name
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(
                f,
                meta=np.array(json.dumps(info, sort_keys=True)),
                x0=x0[index].numpy(),
                goals=goals[index].numpy(),
                inputs=inputs[: out.steps].numpy(),
                states=out.states[:, 0].numpy(),
                present=out.present[:, 0].numpy(),
                collided=out.collided[0].numpy(),
            )
        written.append(path)
    return written


def _scene_fields(scene: FleetScene) -> dict[str, Any]:
    """The scene's fields, JSON-able (per-car tuples as lists)."""
    fields = {name: getattr(scene, name) for name in scene.__dataclass_fields__}
    return {k: list(v) if isinstance(v, tuple) else v for k, v in fields.items()}


def load_episode(path: str | os.PathLike) -> FleetEpisode:
    """The episode file at ``path`` (:func:`save_collided`); read without pickle. A file that is not
    one, lacks an array or holds arrays of shapes that do not fit its scene raises ``ValueError``
    naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"fleet episode file {str(path)!r} does not exist")
    with open(path, "rb") as f:
        if f.read(4) != b"PK\x03\x04":  # np.load would take anything else for a pickle
            raise ValueError(f"{str(path)!r} is not a fleet episode file (not an .npz archive)")
    try:
        with np.load(path, allow_pickle=False) as data:
            found = {k: np.asarray(data[k]) for k in data.files if k in ("meta", *ARRAYS)}
    except (OSError, EOFError, ValueError) as err:
        raise ValueError(f"{str(path)!r} is not a fleet episode file ({err})") from None
    missing = [k for k in ("meta", *ARRAYS) if k not in found]
    if missing:
        raise ValueError(f"fleet episode file {str(path)!r} lacks {', '.join(missing)}")
    arrays = {k: found[k] for k in ARRAYS}
    try:
        meta = json.loads(str(found["meta"]))
    except json.JSONDecodeError as err:
        raise ValueError(f"fleet episode file {str(path)!r}: its meta is not JSON ({err})") from None
    fields = meta.get("scene") if isinstance(meta, dict) else None
    if not isinstance(fields, dict) or not set(fields) <= set(FleetScene.__dataclass_fields__):
        raise ValueError(f"fleet episode file {str(path)!r}: its meta holds no scene of known fields")
    scene = FleetScene(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})
    _check_shapes(path, scene, arrays)
    return FleetEpisode(scene=scene, meta=meta, **arrays)


def _check_shapes(path: Path, scene: FleetScene, a: dict[str, np.ndarray]) -> None:
    n = scene.n_cars
    ticks = a["inputs"].shape[0] if a["inputs"].ndim == 2 else -1
    want = {
        "x0": (3 * n,),
        "goals": (n, 2),
        "inputs": (ticks, n),
        "states": (ticks + 1, 3 * n),
        "present": (ticks + 1, n),
        "collided": (n,),
    }
    for name, shape in want.items():
        if a[name].shape != shape or ticks < 0:
            raise ValueError(f"fleet episode file {str(path)!r}: {name} has shape {a[name].shape}, expected {shape}")
    for name in ("present", "collided"):
        if a[name].dtype != bool:
            raise ValueError(f"fleet episode file {str(path)!r}: {name} must be bool, got {a[name].dtype}")
    for name in ("x0", "goals", "inputs", "states"):
        if a[name].dtype != np.float64 or not np.isfinite(a[name]).all():
            raise ValueError(f"fleet episode file {str(path)!r}: {name} must be finite float64")


def first_collision(episode: FleetEpisode) -> dict[str, Any]:
    """When the episode's first collision happened: ``tick`` (the step after which it was judged),
    ``time`` (s), ``pairs`` (the pairs of cars within the collision radius then, ``(i, j)`` with
    ``i < j``), ``distance`` (their least centre distance) and ``radius`` (the scene's collision
    radius); ``tick``, ``time`` and ``distance`` are ``None`` where no car collided."""
    scene = episode.scene
    present = torch.as_tensor(episode.present)
    # a car that leaves the scene between two ticks either arrived or collided; the collided ones
    left = present[:-1] & ~present[1:] & torch.as_tensor(episode.collided)[None]
    ticks = torch.nonzero(left.any(1)).flatten()
    if ticks.numel() == 0:
        return {"tick": None, "time": None, "pairs": [], "distance": None, "radius": scene.collision_radius}
    tick = int(ticks[0])
    pos = positions(torch.as_tensor(episode.states[tick + 1])[None], scene.n_cars)[0]
    gaps = torch.cdist(pos, pos, compute_mode="donot_use_mm_for_euclid_dist")
    live = present[tick][:, None] & present[tick][None, :]
    close = torch.triu(live & (gaps <= scene.collision_radius), diagonal=1)
    pairs = torch.nonzero(close)
    return {
        "tick": tick + 1,
        "time": (tick + 1) * scene.dt,
        "pairs": [tuple(p) for p in pairs.tolist()],
        "distance": float(gaps[close].min()),
        "radius": scene.collision_radius,
    }


def window_frames(episode: FleetEpisode, seconds: float, every: int, render: Callable[..., np.ndarray]) -> list:
    """Frames of the last ``seconds`` before (and including) the first collision, or of the whole
    episode where none happened, every ``every``-th step: ``render(x, goals, present, scene, time,
    crashed)`` (:func:`reach_envs.fleet_render.render_fleet`)."""
    e, scene = episode, episode.scene
    hit = first_collision(episode)["tick"]
    end = episode.states.shape[0] - 1 if hit is None else hit
    begin = max(0, end - round(seconds / scene.dt))
    picks = list(range(begin, end + 1, every))
    if picks[-1] != end:
        picks.append(end)
    return [render(e.states[k], e.goals, e.present[k], scene, k * scene.dt, e.collided & ~e.present[k]) for k in picks]


def conflict_trace(episode: FleetEpisode, seconds: float, every: int) -> list[dict[str, Any]]:
    """The fleet filter's view of the last ``seconds`` before the first collision, every ``every``-th
    step: for the first colliding pair ``(i, j)``, its distance and pair value, the filter's threshold
    for it, and the group of cars that active pairs join to it (:func:`safety.fleet.graph.components`
    over the pairs within the threshold plus its band): its cars, its active pairs and their least
    value. The filter is the study's (:func:`studies.fleet_methods.fleet_value`, with the episode's
    recorded ``hold``, ``reaction_time`` and ``tie_break``), read at the replayed states. An episode without a
    collision has no trace (``[]``)."""
    hit = first_collision(episode)
    if hit["tick"] is None:
        return []
    scene, meta = episode.scene, episode.meta
    options: dict[str, Any] = {k: float(meta[k]) for k in ("hold", "reaction_time") if k in meta}
    if "tie_break" in meta:
        options["tie_break"] = str(meta["tie_break"])
    fv = fleet_value(scene)
    rule = FleetFilter(fv, FleetFilterSettings(dt=scene.dt, **options))
    t = float(max(s.system.horizon for s in fv.solutions))
    i, j = hit["pairs"][0]
    end = hit["tick"]
    rows = []
    for k in range(max(0, end - round(seconds / scene.dt)), end, every):
        x = torch.as_tensor(episode.states[k])[None]
        c = fv.candidates(x, t, torch.as_tensor(episode.present[k])[None], rule.level)
        theta = rule.threshold[c.first, c.second]
        active = torch.nonzero(c.value <= theta + rule.band[c.first, c.second]).squeeze(-1)
        label = components(scene.n_cars, c.first[active], c.second[active])
        mine = active[label[c.first[active]] == label[i]]
        pair = torch.nonzero(((c.first == i) & (c.second == j)) | ((c.first == j) & (c.second == i))).flatten()
        pos = positions(x, scene.n_cars)[0]
        rows.append(
            {
                "tick": k,
                "time": k * scene.dt,
                "distance": float((pos[i] - pos[j]).norm()),
                "value": float(c.value[pair[0]]) if pair.numel() else None,
                "threshold": float(theta[pair[0]]) if pair.numel() else None,
                "group_cars": int(torch.unique(torch.cat([c.first[mine], c.second[mine]])).numel()),
                "group_pairs": int(mine.numel()),
                "group_least": float(c.value[mine].min()) if mine.numel() else None,
                "inputs": (float(episode.inputs[k, i]), float(episode.inputs[k, j])),
            }
        )
    return rows
