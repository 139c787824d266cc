"""The fleet study (reach fleet-eval): rows with intervals and bounds, resumable, one line per error."""

from __future__ import annotations

import json

import pytest

from reach_cli import main
from reach_envs.fleet_scenes import FleetScene
from studies.fleet_eval import run_fleet_eval
from studies.fleet_plots import plot_fleet_eval, record_fleet_gif
from studies.fleet_settings import FleetEvalSettings

TINY = {"layouts": ("circle-swap",), "sizes": (3,), "episodes": 6, "batch": 3, "timing_ticks": 3}


def test_settings_refuse_bad_values_naming_them():
    for field, bad in (("sizes", (1,)), ("methods", ("magic",)), ("episodes", 0), ("beta", 1.0), ("layouts", ())):
        with pytest.raises(ValueError, match=field):
            FleetEvalSettings(**{field: bad})
    for density in (float("nan"), 0.0, 5.0):  # not finite, not positive, denser than starts 1 apart allow
        with pytest.raises(ValueError, match="density"):
            FleetEvalSettings(density=density)
    for hold in (float("nan"), 0.0, -0.1, float("inf")):
        with pytest.raises(ValueError, match="hold"):
            FleetEvalSettings(hold=hold)
    for reaction in (float("nan"), -0.1, float("inf")):
        with pytest.raises(ValueError, match="reaction_time"):
            FleetEvalSettings(reaction_time=reaction)


def test_the_study_writes_one_row_per_cell_and_a_rerun_resumes(tmp_path):
    settings = FleetEvalSettings(methods=("none", "fleet"), **TINY)
    seen: list[str] = []
    rows = run_fleet_eval(settings, tmp_path / "s", progress=seen.append)
    assert seen == ["circle-swap/3/none", "circle-swap/3/fleet"]
    by = {r["method"]: r for r in rows}
    assert by["none"]["episodes"] == 6 and by["fleet"]["episodes"] == 6
    for r in rows:
        assert 0.0 <= r["collision_low"] <= r["collision_rate"] <= r["collision_high"] <= 1.0
        assert 0.0 <= r["goal_low"] <= r["goal_rate"] <= r["goal_high"] <= 1.0
        assert r["collision_bound"] >= r["collision_rate"]
    assert by["none"]["intervention_rate"] == 0.0
    assert by["fleet"]["intervention_rate"] > 0.0 and by["fleet"]["decision_ms"] > 0.0
    fleet = by["fleet"]
    assert 0 < fleet["decision_ms"] <= fleet["decision_p99_ms"] <= fleet["decision_max_ms"]
    assert 0 < fleet["timed"] <= TINY["timing_ticks"]
    again: list[str] = []
    assert run_fleet_eval(settings, tmp_path / "s", progress=again.append) == rows
    assert again == []  # every cell stored: nothing rerun
    stored = json.loads((tmp_path / "s.json").read_text())
    assert len(stored["results"]) == 2 and (tmp_path / "s.md").read_text().count("circle-swap") == 2
    with pytest.raises(ValueError, match="settings"):
        run_fleet_eval(FleetEvalSettings(methods=("none",), **{**TINY, "episodes": 4}), tmp_path / "s")
    plot_fleet_eval(rows, tmp_path / "p.png")
    assert (tmp_path / "p.png").stat().st_size > 1000


def test_an_episode_gif_says_what_happened(tmp_path):
    out = record_fleet_gif(
        FleetScene(layout="random-goals", n_cars=4, horizon=2.0), "fleet", tmp_path / "e.gif", every=5
    )
    assert (tmp_path / "e.gif").stat().st_size > 1000
    assert out["frames"] >= 2 and out["steps"] <= 40


def test_cli_bad_input_is_one_line_exit_2(tmp_path, capsys):
    assert main(["fleet-eval", "--out", str(tmp_path / "s"), "--methods", "magic"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "magic" in err[0]
    assert main(["fleet-eval", "--out", str(tmp_path / "s"), "--hold", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "hold" in err[0]
    assert main(["fleet-eval", "--out", str(tmp_path / "s"), "--reaction-time", "nan"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "reaction_time" in err[0]
    assert main(["fleet-eval", "--out", str(tmp_path / "s"), "--tie-break", "random"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tie_break" in err[0] and "leximin" in err[0]
    assert main(["fleet-eval", "--out", str(tmp_path / "s"), "--keep-collisions", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "keep_collisions" in err[0]


def test_the_results_record_the_hold_that_ran_and_a_rerun_of_another_is_refused(tmp_path):
    from safety.fleet.greedy import HOLD  # lazy: the filter's default, which a default run records

    run_fleet_eval(FleetEvalSettings(methods=("none",), **TINY), tmp_path / "s")
    assert json.loads((tmp_path / "s.json").read_text())["settings"]["hold"] == HOLD
    with pytest.raises(ValueError, match="settings"):
        run_fleet_eval(FleetEvalSettings(methods=("none",), hold=HOLD / 2, **TINY), tmp_path / "s")
    run_fleet_eval(FleetEvalSettings(methods=("none",), hold=HOLD, **TINY), tmp_path / "s")  # the same: resumes


def test_the_results_record_the_reaction_time_and_it_reaches_the_filter(tmp_path, monkeypatch):
    """A default run records the filter's own reaction time; another one is refused from the same
    file; and the value given is the one the fleet filter is built with."""
    from safety.fleet.filter import REACTION_TIME  # lazy: the filter's default, which a default run records
    from studies import fleet_methods  # lazy: this test watches the settings the study builds

    built = []
    real = fleet_methods.FleetFilterSettings

    def watched(*args, **kwargs):
        built.append(real(*args, **kwargs))
        return built[-1]

    monkeypatch.setattr(fleet_methods, "FleetFilterSettings", watched)
    run_fleet_eval(FleetEvalSettings(methods=("fleet",), **{**TINY, "timing_ticks": 0}), tmp_path / "s")
    assert json.loads((tmp_path / "s.json").read_text())["settings"]["reaction_time"] == REACTION_TIME
    assert built[-1].reaction_time == REACTION_TIME
    with pytest.raises(ValueError, match="settings"):
        run_fleet_eval(FleetEvalSettings(methods=("none",), reaction_time=1.0, **TINY), tmp_path / "s")
    run_fleet_eval(
        FleetEvalSettings(methods=("fleet",), reaction_time=1.0, **{**TINY, "timing_ticks": 0}), tmp_path / "r"
    )
    assert built[-1].reaction_time == 1.0
    assert json.loads((tmp_path / "r.json").read_text())["settings"]["reaction_time"] == 1.0
    # the tie-break likewise: the default recorded, the one given built and recorded
    assert json.loads((tmp_path / "s.json").read_text())["settings"]["tie_break"] == "centre"
    run_fleet_eval(
        FleetEvalSettings(methods=("fleet",), tie_break="leximin", **{**TINY, "timing_ticks": 0}), tmp_path / "t"
    )
    assert built[-1].tie_break == "leximin"
    assert json.loads((tmp_path / "t.json").read_text())["settings"]["tie_break"] == "leximin"
    with pytest.raises(ValueError, match="tie_break"):
        FleetEvalSettings(tie_break="random")


def test_a_stem_with_a_dot_keeps_it(tmp_path):
    run_fleet_eval(FleetEvalSettings(methods=("none",), **TINY), tmp_path / "density_0.2")
    assert (tmp_path / "density_0.2.json").exists() and (tmp_path / "density_0.2.md").exists()
    assert not (tmp_path / "density_0.json").exists()


def test_the_study_refuses_a_pair_grid_whose_verdict_fails(monkeypatch):
    from studies import fleet_methods  # lazy: this test patches the module's view of the cards
    from training import pretrained

    failing = pretrained.card("dubins3d").verdict  # a computed verdict that fails the bar
    assert not failing.passes
    monkeypatch.setattr(pretrained, "source_verdict", lambda source: failing)
    fleet_methods._shipped_pair.cache_clear()
    try:
        with pytest.raises(ValueError, match="trust bar"):
            fleet_methods.make_method("fleet", FleetScene(layout="circle-swap", n_cars=3))
    finally:
        fleet_methods._shipped_pair.cache_clear()


def test_timing_past_the_episode_stops_at_its_horizon():
    from studies.fleet_eval import decision_times  # lazy: only this test times decisions directly
    from studies.fleet_methods import make_method  # lazy: as above

    # cars that never arrive keep the episode alive: timing must stop at the horizon, not run on
    scene = FleetScene(layout="circle-swap", n_cars=3, horizon=0.5)
    times = decision_times(scene, make_method("fleet", scene), 10**9, seed=0)
    assert times["timed"] == scene.max_steps == 10
