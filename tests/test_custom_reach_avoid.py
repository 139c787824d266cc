"""A reach-avoid system defined outside the package (examples/my_systems.py: DubinsGap) goes through
the grid, training, verification, the env, the filter and a sweep from Python, and through all but
the sweep (whose command line is kind-blind, tested in test_custom_systems.py) from the command
line, at toy size; its run reloads in a new process. The tutorial (docs/custom_system.md) runs the
same commands at full size."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SYSTEM = "my_systems:DubinsGap"


def _env() -> dict[str, str]:
    path = os.environ.get("PYTHONPATH")
    return {
        **os.environ,
        "PYTHONPATH": str(ROOT / "examples") + (os.pathsep + path if path else ""),
        "TQDM_DISABLE": "1",
        "MPLBACKEND": "Agg",
    }


def _run(*args: str) -> str:
    done = subprocess.run(args, capture_output=True, text=True, env=_env(), cwd=ROOT)
    assert done.returncode == 0, f"{' '.join(args)} failed ({done.returncode}):\n{done.stderr[-2000:]}"
    return done.stdout


@pytest.mark.slow  # run by name in .ci/run: keeps the default suite under 10 minutes
def test_the_python_tour_runs_every_tool(tmp_path):
    out = _run(sys.executable, str(ROOT / "examples" / "reach_avoid_tour.py"), str(tmp_path), "--tiny")
    assert "verification: false reachable" in out and "filtered episode:" in out
    assert "sweep:" in out and "(0 failed)" in out
    assert out.strip().splitlines()[-1] == "reloaded in a new process: reach-avoid my_systems:DubinsGap"


@pytest.mark.slow  # run by name in .ci/run: keeps the default suite under 10 minutes
def test_the_command_line_runs_every_tool(tmp_path):
    gt, run = str(tmp_path / "gt.npz"), str(tmp_path / "run")
    _run("reach", "groundtruth", SYSTEM, "--grid", "21", "--times", "0,0.5,1,1.5", "--out", gt)
    _run(
        "reach", "train", "--system", SYSTEM, "--steps", "10", "--layout", "ssl", "--width", "16",
        "--points", "256", "--compile", "off", "--out", run,
    )  # fmt: skip
    _run(
        "reach", "evaluate", run, gt, "--system", SYSTEM, "--ground-truth", gt, "--samples", "200",
        "--scenario-samples", "50", "--robust-samples", "0", "--out", str(tmp_path / "eval.csv"),
    )  # fmt: skip
    rows = json.loads((tmp_path / "eval.json").read_text())["results"]
    assert {r["problem"] for r in rows} == {"reach-avoid"} and all("false_reachable_rate" in r for r in rows)
    assert "false reachable %" in (tmp_path / "eval.md").read_text()
    _run(
        "reach", "filter-eval", gt, "--system", SYSTEM, "--filters", "switch", "--pursuer",
        "worst-case", "--adversary", gt, "--start-outside", gt, "--episodes", "10",
        "--out", str(tmp_path / "filter.csv"),
    )  # fmt: skip
    with open(tmp_path / "filter.csv") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 2 and all(r["goal_rate"] not in ("", "nan") for r in table)
    # the sweep's command line is the avoid systems' (test_custom_systems.py); the Python tour sweeps this one
