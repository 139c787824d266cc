"""Collided episodes of the fleet study, kept to replay alone (studies.fleet_collisions, reach fleet-replay)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from reach_cli import main
from reach_envs.fleet import goal_seeking, rollout
from reach_envs.fleet_scenes import FleetScene
from studies.fleet_collisions import InputRecorder, conflict_trace, first_collision, load_episode, replay
from studies.fleet_eval import collisions_folder, run_fleet_eval
from studies.fleet_methods import make_method
from studies.fleet_settings import FleetEvalSettings


def test_an_episode_of_a_filtered_batch_replays_alone_bit_for_bit():
    """The fleet filter's stacked QP couples a batch's episodes in the last digits; the inputs an
    episode was given replay its states exactly, alone."""
    scene = FleetScene(layout="circle-swap", n_cars=16, horizon=8.0)
    decide = make_method("fleet", scene)

    def controller(x, goals, present):
        return decide(x, goal_seeking(x, goals, scene), present)[0]

    x0, goals = scene.sample(3, np.random.default_rng(0))
    recorder = InputRecorder(controller)
    batch = rollout(scene, x0, goals, recorder, record=True)
    assert len(recorder.inputs) == batch.steps
    for i in range(3):
        alone = replay(scene, x0[i], goals[i], recorder.episode(i))
        ticks = alone.states.shape[0]
        assert torch.equal(alone.states[:, 0], batch.states[:ticks, i])
        assert torch.equal(alone.collided[0], batch.collided[i])


def test_the_study_keeps_the_collided_episodes_and_each_replays(tmp_path):
    settings = FleetEvalSettings(
        layouts=("circle-swap",), sizes=(8,), methods=("none",), episodes=4, batch=2, timing_ticks=0, keep_collisions=4
    )
    (row,) = run_fleet_eval(settings, tmp_path / "s")
    files = sorted(collisions_folder(tmp_path / "s").glob("*.npz"))
    assert row["collisions"] > 0 and len(files) == row["collisions"]  # unfiltered circle swaps collide
    scene = FleetScene(layout="circle-swap", n_cars=8)
    for path in files:
        episode = load_episode(path)
        assert episode.scene == scene and episode.meta["method"] == "none"
        # the file's states are the batch's: the same draw, re-run as the study ran it
        x0, goals = scene.sample(episode.meta["batch_episodes"], np.random.default_rng(episode.meta["seed"]))
        batch = rollout(scene, x0, goals, record=True)
        i, ticks = episode.meta["index"], episode.states.shape[0]
        assert np.array_equal(episode.states, batch.states[:ticks, i].numpy())
        hit = first_collision(episode)
        assert hit["tick"] is not None and hit["pairs"] and hit["distance"] <= scene.collision_radius
        # nobody collided before: every pair present one step earlier was apart
        pos = episode.states[hit["tick"] - 1][: 2 * scene.n_cars].reshape(scene.n_cars, 2)
        alive = episode.present[hit["tick"] - 1]
        gaps = np.linalg.norm(pos[:, None] - pos[None], axis=-1)[np.ix_(alive, alive)]
        assert (gaps[np.triu_indices(int(alive.sum()), 1)] > scene.collision_radius).all()


def test_the_study_keeps_at_most_keep_collisions_per_cell_and_the_results_do_not_depend_on_it(tmp_path):
    base = {"layouts": ("circle-swap",), "sizes": (4,), "methods": ("none",), "episodes": 5, "batch": 2}
    (row,) = run_fleet_eval(FleetEvalSettings(**base, timing_ticks=0, keep_collisions=3), tmp_path / "s")
    names = sorted(p.name for p in collisions_folder(tmp_path / "s").glob("*.npz"))
    assert row["collisions"] == 5 and names == [
        "circle-swap-4-none-seed0-ep0.npz",
        "circle-swap-4-none-seed0-ep1.npz",
        "circle-swap-4-none-seed1000-ep0.npz",
    ]  # the first three, across batches
    # another count continues the same results file (it is not a setting of the rows)
    assert run_fleet_eval(FleetEvalSettings(**base, timing_ticks=0, keep_collisions=0), tmp_path / "s") == [row]
    run_fleet_eval(FleetEvalSettings(**base, timing_ticks=0, keep_collisions=0), tmp_path / "t")
    assert not collisions_folder(tmp_path / "t").exists()
    with pytest.raises(ValueError, match="keep_collisions"):
        FleetEvalSettings(keep_collisions=-1)


def test_fleet_replay_prints_the_collision_and_draws_it(tmp_path, capsys):
    settings = FleetEvalSettings(
        layouts=("circle-swap",), sizes=(4,), methods=("none",), episodes=1, batch=1, timing_ticks=0
    )
    run_fleet_eval(settings, tmp_path / "s")
    (path,) = collisions_folder(tmp_path / "s").glob("*.npz")
    gif = tmp_path / "c.gif"
    assert main(["fleet-replay", str(path), "--gif", str(gif), "--seconds", "1", "--every", "2", "--trace", "5"]) == 0
    out = capsys.readouterr().out
    assert "collided at t =" in out and "car_" in out and gif.stat().st_size > 1000
    assert len([line for line in out.splitlines() if line.count("|") == 3]) == 1 + 4  # header, 20 steps / 5


def test_the_trace_follows_the_colliding_pair_into_its_collision(tmp_path):
    settings = FleetEvalSettings(
        layouts=("circle-swap",), sizes=(8,), methods=("none",), episodes=1, batch=1, timing_ticks=0
    )
    run_fleet_eval(settings, tmp_path / "s")
    (path,) = collisions_folder(tmp_path / "s").glob("*.npz")
    episode = load_episode(path)
    rows = conflict_trace(episode, 1.0, 1)
    assert len(rows) == 20 and rows[-1]["tick"] == first_collision(episode)["tick"] - 1
    radius = episode.scene.collision_radius
    assert rows[-1]["distance"] < rows[0]["distance"] and radius < rows[-1]["distance"] < radius + 0.1
    last = rows[-1]  # one step before the collision the pair is read, active, and in a group with both cars
    assert last["value"] is not None and last["value"] <= last["threshold"] and last["group_cars"] >= 2
    assert last["group_least"] <= last["value"]


def _tampered(tmp_path, path, name, **change):
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(change)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    bad = tmp_path / f"{name}.npz"
    np.savez(bad, **arrays)
    return bad


def test_a_malformed_episode_file_is_refused_in_one_line(tmp_path, capsys):
    settings = FleetEvalSettings(
        layouts=("circle-swap",), sizes=(4,), methods=("none",), episodes=1, batch=1, timing_ticks=0
    )
    run_fleet_eval(settings, tmp_path / "s")
    (path,) = collisions_folder(tmp_path / "s").glob("*.npz")
    with np.load(path, allow_pickle=False) as data:
        states, meta = data["states"], json.loads(str(data["meta"]))
    nan = states.copy()
    nan[3, 0] = np.nan
    meta["scene"]["n_cars"] = 5
    odd = json.loads(json.dumps(meta))
    odd["scene"]["wings"] = 2
    text = tmp_path / "text.npz"
    text.write_text("not an archive")
    cases = {
        "states": _tampered(tmp_path, path, "nan", states=nan),
        "lacks inputs": _tampered(tmp_path, path, "lacks", inputs=None),
        "x0 has shape": _tampered(tmp_path, path, "cars", meta=np.array(json.dumps(meta))),
        "no scene of known fields": _tampered(tmp_path, path, "odd", meta=np.array(json.dumps(odd))),
        "meta is not JSON": _tampered(tmp_path, path, "json", meta=np.array("{not json")),
        "not an .npz": text,
        "does not exist": tmp_path / "none.npz",
    }
    for needle, bad in cases.items():
        with pytest.raises(ValueError, match=needle):
            load_episode(bad)
        assert main(["fleet-replay", str(bad)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0]
