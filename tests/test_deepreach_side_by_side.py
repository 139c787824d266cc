"""The DeepReach side-by-side harness (benchmarks/deepreach_side_by_side.py) poses our problem to DeepReach
and refuses bad settings before anything trains. (Its end-to-end run needs DeepReach's code; see
docs/results/training.md.)"""

from __future__ import annotations

import argparse
import importlib.util
import math
from pathlib import Path

import pytest

from reach.systems import make_system

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location(
    "deepreach_side_by_side", ROOT / "benchmarks" / "deepreach_side_by_side.py"
)
harness = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(harness)


def _options(args: list[str]) -> dict[str, str]:
    return dict(zip(args[0::2], args[1::2], strict=True))


def test_air3d_is_posed_with_our_constants_and_horizon():
    system = make_system("air3d")
    _, args = harness.deepreach_problem("air3d")
    opts = _options(args)
    assert opts["--dynamics_class"] == "Air3D"
    assert float(opts["--collisionR"]) == system.collision_radius
    assert float(opts["--velocity"]) == system.evader_speed
    assert float(opts["--omega_max"]) == system.evader_max_turn_rate
    assert math.isclose(float(opts["--angle_alpha_factor"]) * math.pi, system.deepreach.state_scale[2])
    assert float(opts["--tMax"]) == system.horizon
    assert opts["--minWith"] == "target"


def test_the_reach_avoid_rocket_is_posed_at_our_horizon():
    system, args = harness.deepreach_problem("reachavoidrocketlanding")
    opts = _options(args)
    assert opts["--dynamics_class"] == "ReachAvoidRocketLanding"
    assert float(opts["--tMax"]) == system.horizon


def test_a_system_without_a_counterpart_is_refused_by_name():
    with pytest.raises(ValueError, match="dubins3d"):
        harness.deepreach_problem("dubins3d")


@pytest.mark.parametrize(
    "text", ["num_epochs", "=3", "mode=test", "experiments_dir=/x", "model=relu", "model_mode=rbf"]
)
def test_deepreach_args_that_would_break_the_run_or_the_import_are_refused(text):
    with pytest.raises(argparse.ArgumentTypeError):
        harness.key_value(text)


def test_free_deepreach_args_pass_through():
    assert harness.key_value("num_epochs=600") == ("num_epochs", "600")
    assert harness.key_value("model=sine") == ("model", "sine")


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--budget", "ten minutes"], "duration"),
        (["--systems", "air3d,quadrotor"], "quadrotor"),
        (["--threads", "0"], "threads"),
    ],
)
def test_bad_settings_stop_before_any_work(argv, says, tmp_path):
    with pytest.raises(SystemExit, match=says):
        harness.main([*argv, "--out", str(tmp_path / "out"), "--deepreach-git", str(tmp_path / "missing")])
    assert not (tmp_path / "out").exists()
