"""benchmarks/training_domain_ab.py: each arm draws its points from its own box, in its own process
only; a run of another length and a malformed ``--widen`` are refused; the score names where wrong
claims went (smoke size)."""

from __future__ import annotations

import pytest

from reach.systems import ParameterizedVertDrone2D, ReachAvoidRocketLanding
from training import sampling

WIDE = ["y=0:150", "vy=-343.43:200", "w=-85:85"]


@pytest.fixture()
def ab(monkeypatch):
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import training_domain_ab

    return training_domain_ab


def test_each_arm_draws_from_its_box_and_the_hook_is_restored(ab, tmp_path, monkeypatch):
    boxes = []
    real = sampling.training_box
    monkeypatch.setattr(sampling, "training_box", lambda system: boxes.append(real(system)) or boxes[-1])
    rocket = ReachAvoidRocketLanding()
    ab.train("reachavoidrocketlanding", "domain", 2, 1, tmp_path / "box")
    ab.train("reachavoidrocketlanding", "domain", 2, 1, tmp_path / "wide", WIDE)
    x, _, th, vx, _, _ = rocket.domain
    assert boxes == [rocket.domain, (x, (0.0, 150.0), th, vx, (-343.43, 200.0), (-85.0, 85.0))]
    assert ReachAvoidRocketLanding().training_domain() == rocket.domain  # the swap ended with the arm
    with pytest.raises(SystemExit, match="a run of 2 steps, not 3"):
        ab.train("reachavoidrocketlanding", "domain", 3, 1, tmp_path / "box")


def test_a_declared_training_domain_is_kept_and_restored(ab, tmp_path):
    drone = ParameterizedVertDrone2D()
    assert ab.widened_box(drone, "training-domain", []) == drone.training_domain() != drone.domain
    assert ab.widened_box(drone, "domain", ["z=-1:4"])[1] == (-1.0, 4.0)
    ab.train("parameterizedvertdrone2d", "domain", 1, 1, tmp_path / "drone")
    assert ParameterizedVertDrone2D().training_domain() == drone.training_domain()


@pytest.mark.parametrize(
    ("item", "match"),
    [
        ("q=0:1", "NAME one of x, y, th, vx, vy, w, got 'q=0:1'"),
        ("y=0", "NAME=LOW:HIGH"),
        ("y=a:1", "LOW and HIGH must be numbers"),
    ],
)
def test_a_malformed_widening_is_refused(ab, item, match):
    with pytest.raises(SystemExit, match=match):
        ab.widened_box(ReachAvoidRocketLanding(), "domain", [item])


def test_the_score_lists_wrong_claims_and_their_exits(ab, tmp_path, capsys):
    ab.train("reachavoidrocketlanding", "domain", 2, 1, tmp_path / "box")
    ab.score([str(tmp_path / "box")], samples=300, seed=0, threads=1, base="domain", widen=WIDE)
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {tmp_path}")]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    claims, wrong = float(cells[1]), float(cells[2])
    assert 0 <= wrong <= claims <= 100 and cells[3].endswith(f"of {min(2000, round(3 * wrong))}")
    assert 0 <= float(cells[4]) <= float(cells[3].split()[0])  # the wider box holds the domain


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["train", "--system", "rocketlanding", "--steps", "0", "--out", "OUT"],
            "argument --steps: must be >= 1, got 0",
        ),
        (["score", "pretrained:rocketlanding", "--samples", "-5"], "argument --samples: must be >= 1, got -5"),
        (
            ["score", "pretrained:rocketlanding", "no-such-run"],
            "training_domain_ab: no-such-run: no such file or directory",
        ),
    ],
)
def test_bad_arguments_stop_in_one_line_before_any_work(args, message, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "training_domain_ab.py"
    args = [str(tmp_path / "out") if a == "OUT" else a for a in args]
    done = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1].endswith(message)
    assert not (tmp_path / "out").exists()
