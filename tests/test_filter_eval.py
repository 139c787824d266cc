"""Filter evaluation over episodes: control experiments, PettingZoo = vector, the CLI end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from reach.systems import Air3D, MultiVehicle9D
from reach_cli import main
from safety import worst_case_disturbance
from studies.filter_configs import FilterConfig
from studies.filter_episodes import evaluate_filter_parallel, evaluate_filters, outside_states
from studies.goal_tasks import EvaderGoalTask, WaypointTask
from training import NeuralValueFunction, ValueNetwork


def test_grid_filter_stops_worst_case_attacks_from_outside_the_brt(air3d_grid):
    starts = outside_states(air3d_grid, 400, 0.1, seed=0)
    assert (air3d_grid.value(torch.as_tensor(starts), 1.1) > 0.1).all()
    overrides = {"disturbance": worst_case_disturbance(air3d_grid)}
    rows = evaluate_filters(
        "air3d",
        [FilterConfig("nominal"), FilterConfig("grid", air3d_grid)],
        episodes=400,
        seed=0,
        scene_overrides=overrides,
        initial_states=starts,
    )
    nominal, filtered = rows
    assert nominal["collision_rate"] > 0.05  # the attack works on the unfiltered evader
    assert filtered["collision_rate"] == 0.0
    assert filtered["threshold"] == pytest.approx(0.06)  # 2 x (0.75 + 0.75) x 0.02
    assert 0 < filtered["intervention_rate"] < 0.5 and filtered["mean_input_change"] > 0
    assert nominal["intervention_rate"] == 0 and nominal["mean_input_change"] == 0
    assert 0 < filtered["goal_rate"] <= 1 and 0 < filtered["mean_goal_time"] <= 1.1


def test_untrained_network_shows_its_failure():
    torch.manual_seed(0)
    vf = NeuralValueFunction(ValueNetwork(MultiVehicle9D(), "ssssl", width=16))
    nominal, filtered = evaluate_filters(
        "three-car-merge", [FilterConfig("nominal"), FilterConfig("untrained", vf, 0.1)], episodes=30, seed=0
    )
    assert nominal["collision_rate"] == 1.0  # the merge is a pile-up without a filter
    assert filtered["collision_rate"] > 0.5  # a network that knows nothing does not fix it, visibly


@pytest.mark.parametrize("scene", ["three-car-crossing", "head-on"])
def test_pettingzoo_path_gives_the_vector_numbers(scene):
    torch.manual_seed(1)
    from reach_envs.scenes import make_scene

    system = make_scene(scene).system
    vf = NeuralValueFunction(ValueNetwork(system if scene == "head-on" else MultiVehicle9D(), "ssrsl", width=16))
    for config in (FilterConfig("nominal"), FilterConfig("net", vf, 0.2)):
        (vector,) = evaluate_filters(scene, [config], episodes=12, seed=3)
        parallel = evaluate_filter_parallel(scene, config, episodes=12, seed=3)
        for key in ("collision_rate", "intervention_rate", "goal_rate", "mean_input_change"):
            assert parallel[key] == pytest.approx(vector[key], abs=1e-9), key


def test_tasks_steer_toward_goals():
    task = WaypointTask(MultiVehicle9D())
    x = np.array([[0.0, 0.0, 0.5, 0.5, -0.5, 0.5, 0.0, np.pi / 2, -np.pi / 2]])
    task.reset(x, np.random.default_rng(0))
    assert np.allclose(task.goals[0, 0], [1.0, 0.0]) and np.allclose(task.goals[0, 1], [0.5, 1.5])
    assert np.allclose(task.nominal_actions(x), 0.0)  # already pointing at their goals
    from reach.systems import Air3D

    evader = EvaderGoalTask(Air3D(), spread=0.0)
    evader.reset(np.zeros((2, 3)), np.random.default_rng(0))
    # a full-rate turn for 0.5 s traces an exact arc of radius v / w
    evader.advance(np.zeros((2, 3)), np.array([[3.0], [0.0]]), 0.5, np.array([True, True]), 0.5)
    r = 0.75 / 3.0
    assert evader.pose[0] == pytest.approx([r * np.sin(1.5), r * (1 - np.cos(1.5)), 1.5])
    assert evader.pose[1] == pytest.approx([0.375, 0.0, 0.0])


@pytest.mark.slow  # run by name in .ci/run: keeps the default suite under 10 minutes
def test_filter_eval_cli(air3d_grid, tmp_path: Path, capsys):
    grid = tmp_path / "air3d.npz"
    air3d_grid.save(grid)
    out = tmp_path / "fe.csv"
    args = ["filter-eval", str(grid), "--episodes", "60", "--thresholds", "0.03,0.1", "--pursuer", "worst-case"]
    assert main([*args, "--start-outside", str(grid), "--out", str(out), "--gif", str(tmp_path / "fe.gif")]) == 0
    table = capsys.readouterr().out
    assert "| configuration | threshold | collision % [95 % CI] |" in table
    data = json.loads(out.with_suffix(".json").read_text())
    assert [r["label"] for r in data["results"]] == ["nominal", "air3d greedy @ 0.03", "air3d greedy @ 0.1"]
    assert data["pursuer"] == "worst-case" and data["path"] == "vector"
    assert (tmp_path / "fe_tradeoff.png").stat().st_size > 5000
    assert (tmp_path / "fe.gif").stat().st_size > 10000
    assert main(["filter-eval", "--scene", "three-car-merge", "--pursuer", "random", "--out", str(out)]) == 2
    assert "no disturbance" in capsys.readouterr().err


def test_unknown_start_source_is_refused_before_any_episode(tmp_path: Path, capsys):
    """start_from names where --start-outside draws from; anything else fails with the bad value."""
    from studies.filter_study import run_filter_study

    vf = NeuralValueFunction(ValueNetwork(MultiVehicle9D(), "ssssl", width=16))
    with pytest.raises(ValueError, match=r"start_from must be one of .*'nowhere'"):
        run_filter_study("three-car-merge", [], tmp_path / "f.csv", episodes=2, start_outside=vf, start_from="nowhere")
    assert not (tmp_path / "f.csv").exists()
    argv = ["filter-eval", "--scene", "three-car-merge", "--start-from", "nowhere", "--out", str(tmp_path / "g.csv")]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "--start-from" in capsys.readouterr().err


def test_a_bad_backup_horizon_is_refused_before_any_episode(tmp_path: Path, capsys):
    """The lookahead's backup horizon is checked when the configuration is made (library) and when
    the arguments are parsed (CLI), before the nominal episodes run."""
    from studies.filter_study import run_filter_study

    vf = NeuralValueFunction(ValueNetwork(Air3D(), "ssssl", width=16))
    with pytest.raises(ValueError, match=r"backup_horizon .*-0.5"):
        FilterConfig("air3d", vf, 0.0, kind="lookahead", backup_horizon=-0.5)
    with pytest.raises(ValueError, match=r"backup_horizon .*nan"):
        run_filter_study(
            "air3d", [("air3d", vf)], tmp_path / "f.csv", episodes=2, kinds=("lookahead",), backup_horizon=float("nan")
        )
    assert not (tmp_path / "f.csv").exists()
    argv = ["filter-eval", "--scene", "air3d", "--backup-horizon", "-1", "--out", str(tmp_path / "g.csv")]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "--backup-horizon" in capsys.readouterr().err


def test_filter_eval_merges_rows_of_the_same_episodes_and_refuses_others_before_any_episode(
    air3d_grid, tmp_path: Path, capsys, monkeypatch
):
    """A second `reach filter-eval` into the same --out adds its rows (it erased the first's before);
    a rerun of a configuration replaces its row; a table of other episodes is refused, naming the
    setting, before a single episode runs."""
    import studies.filter_study as filter_study

    grid = tmp_path / "air3d.npz"
    air3d_grid.save(grid)
    other = tmp_path / "other.npz"
    air3d_grid.save(other)
    out = tmp_path / "fe.csv"
    base = ["filter-eval", "--episodes", "12", "--out", str(out)]
    assert main([*base, str(grid), "--thresholds", "0.05"]) == 0
    first = json.loads(out.with_suffix(".json").read_text())["results"]
    assert main([*base, str(other), "--thresholds", "0.05", "--filters", "switch,smooth"]) == 0
    data = json.loads(out.with_suffix(".json").read_text())
    labels = [r["label"] for r in data["results"]]
    assert labels == ["nominal", "air3d greedy @ 0.05", "other greedy @ 0.05", "other smooth @ 0.05 g5"]
    assert data["filters"] == ["switch", "smooth"]
    assert data["results"][1] == first[1]  # the first invocation's row, untouched
    assert data["results"][0]["collision_rate"] == first[0]["collision_rate"]  # the same nominal episodes
    assert "other smooth @ 0.05 g5" in capsys.readouterr().out  # the printed table is the merged one
    assert main([*base, str(grid), "--thresholds", "0.05"]) == 0  # a rerun replaces its own row only
    assert [r["label"] for r in json.loads(out.with_suffix(".json").read_text())["results"]] == labels

    def no_episodes(*args, **kwargs):
        raise AssertionError("episodes ran before the table was checked")

    monkeypatch.setattr(filter_study, "evaluate_filters", no_episodes)
    for changed, setting in ((["--episodes", "13"], "episodes"), (["--seed", "4"], "seed")):
        assert main([*base, *changed, str(grid), "--thresholds", "0.05"]) == 2
        err = capsys.readouterr().err
        assert f"({setting}: " in err and "other episodes" in err and len(err.strip().splitlines()) == 1
    out.with_suffix(".json").write_text("{not json")
    assert main([*base, str(grid)]) == 2
    assert "unreadable" in capsys.readouterr().err
