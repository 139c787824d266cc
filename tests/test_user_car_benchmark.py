"""The user-written reach-avoid car of benchmarks/user_car_ten_minutes.py: a valid system for every
tool, and the benchmark runs end to end (smoke size: a 21^3 grid, a few steps)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture()
def windy_car(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import user_car_ten_minutes

    return user_car_ten_minutes.WindyCar


def test_the_user_car_is_a_reach_avoid_problem_with_its_own_geometry(windy_car):
    from reach.systems import DubinsReachAvoid

    car = windy_car()
    assert car.kind == "reach-avoid" and car.problem.has_constraint
    # not the built-in car the defaults were measured on
    assert car.physics_config() != DubinsReachAvoid().physics_config()
    goal = torch.tensor([[0.8, 0.3, 0.0]])
    obstacle = torch.tensor([[0.2, 0.1, 0.0]])
    assert car.target_margin(goal).item() < 0 < car.target_margin(obstacle).item()
    assert car.constraint_margin(obstacle).item() < 0 < car.constraint_margin(goal).item()


def test_the_benchmark_trains_and_scores_against_a_grid(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT / "benchmarks"), "TQDM_DISABLE": "1", "OMP_NUM_THREADS": "1"}
    gt = tmp_path / "gt21.npz"
    solve = [sys.executable, "-m", "reach", "--threads", "1", "groundtruth", "user_car_ten_minutes:WindyCar"]
    done = subprocess.run([*solve, "--grid", "21", "--out", str(gt)], capture_output=True, text=True, cwd=ROOT, env=env)
    assert done.returncode == 0, done.stderr
    bench = [sys.executable, "benchmarks/user_car_ten_minutes.py", "--steps", "5", "--threads", "1", "--gt", str(gt)]
    run = tmp_path / "run"
    done = subprocess.run([*bench, "--recipe", "points=256", "--out", str(run)], capture_output=True, text=True,
                          cwd=ROOT, env=env)  # fmt: skip
    assert done.returncode == 0, done.stderr
    score = json.loads((run / "score.json").read_text())
    assert score["steps"] == 5 and score["recipe"] == {"points": 256}
    assert 0 <= score["iou_volume"] <= 1 and score["mse_volume"] > 0
    assert "volume IoU" in done.stdout


def test_a_recipe_without_a_value_stops_in_one_line(tmp_path):
    done = subprocess.run(
        [sys.executable, "benchmarks/user_car_ten_minutes.py", "--recipe", "points", "--out", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert done.returncode != 0 and "--recipe expects KEY=VALUE, got 'points'" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "r").exists()
