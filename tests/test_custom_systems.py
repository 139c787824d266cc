"""A user's own system through every tool: registration, import paths, construction checks, and the
tutorial's path (grid, training, verification, filter, sweep) at toy size, from Python and the CLI.

The systems live outside the package, in ``examples/my_systems.py`` (the tutorial's file).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from reach.systems import TORCH, Box, ControlAffineSystem, make_system, register_system, system_from_config
from reach.systems.registry import SYSTEMS
from reach_cli import main

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
if str(EXAMPLES) not in sys.path:
    sys.path.insert(0, str(EXAMPLES))

import my_systems  # noqa: E402
from my_systems import DubinsAccel, DubinsAvoid  # noqa: E402

TINY = {"width": 16, "points": 256, "log_every": 5, "checkpoint_every_s": 0.0}


# ---------------------------------------------------------------------- registration and references
def test_registered_names_and_import_paths_resolve_to_the_same_class():
    by_name = make_system("dubins-avoid")
    by_path = make_system("my_systems:DubinsAvoid")
    assert type(by_name) is type(by_path) is DubinsAvoid
    assert make_system(DubinsAccel, wind=0.02).wind == 0.02
    instance = DubinsAvoid(radius=0.3)
    assert make_system(instance) is instance
    # configs store the import path: a fresh process finds the class from it
    assert instance.config() == {"name": "my_systems:DubinsAvoid", "parameters": instance.parameters()}
    assert system_from_config(instance.config()) == instance
    # built-ins keep their short registered names
    assert make_system("air3d").config()["name"] == "air3d"


def test_register_system_refuses_a_taken_name_and_defaults_the_name():
    class Another(DubinsAvoid):
        name = "dubins-avoid"

    with pytest.raises(ValueError, match=r"dubinsavoid.*taken by my_systems:DubinsAvoid"):
        register_system(Another)
    register_system(DubinsAvoid)  # the same class again (a module imported twice) is fine

    @register_system(name="plain-dubins-test")
    class PlainDubins(DubinsAvoid):
        pass

    try:
        assert make_system("plain_dubins_test").name == "plaindubinstest"
    finally:
        SYSTEMS.pop("plaindubinstest")

    class Unnamed(DubinsAvoid):
        pass

    assert Unnamed.name == "unnamed"
    with pytest.raises(TypeError, match="ControlAffineSystem subclass"):
        register_system(dict)


@pytest.mark.parametrize(
    ("reference", "message"),
    [
        ("no_such_module_xyz:Thing", "cannot import module 'no_such_module_xyz'"),
        ("my_systems:NoSuchClass", "has no 'NoSuchClass'"),
        ("my_systems:math", "not a ControlAffineSystem subclass"),
        ("my systems:Dubins", "looks like 'package.module:Name'"),
        ("dubins-nowhere", "unknown system 'dubins-nowhere'"),
    ],
)
def test_bad_references_name_themselves(reference, message):
    with pytest.raises(ValueError, match=message):
        make_system(reference)


def test_import_paths_read_from_files_are_imported_only_when_trusted(monkeypatch):
    """A checkpoint or .npz must not choose which module runs: an import path from a file is
    resolved only for an imported module, a trusted one, or one the caller named."""
    config = {"name": "json.decoder:JSONDecoder", "parameters": {}}
    with pytest.raises(ValueError, match="not a ControlAffineSystem"):
        system_from_config(config)  # already imported: found, then refused as no system
    monkeypatch.delitem(sys.modules, "my_systems")
    with pytest.raises(ValueError, match=r"importing 'my_systems' would run its code.*REACH_TRUSTED_MODULES"):
        system_from_config({"name": "my_systems:DubinsAvoid", "parameters": {}})
    monkeypatch.setenv("REACH_TRUSTED_MODULES", "other, my_systems")
    assert system_from_config({"name": "my_systems:DubinsAvoid", "parameters": {}}).name == "dubinsavoid"


# ---------------------------------------------------------------------- bad definitions fail when built
class _Base(ControlAffineSystem):
    state_names = ("a", "b")
    periodic = (False, False)

    def __init__(self, **changes):
        self.domain = ((-1.0, 1.0), (-1.0, 1.0))
        self.control_bounds = Box.symmetric([1.0])
        self.horizon = 1.0
        self.matrix = {(1, 0): 1.0}
        self.margin_shape = None
        self.__dict__.update(changes)

    def drift(self, x, xp):
        return [x[1], 0.0 * x[0]]

    def control_matrix(self, x, xp):
        return self.matrix

    def failure_margin_columns(self, x, xp):
        out = x[0] ** 2 + x[1] ** 2 - 0.25
        return out if self.margin_shape is None else out.reshape(self.margin_shape)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"domain": ((-1.0, 1.0),)}, r"state_names \(2\), domain \(1\)"),
        ({"domain": ((-1.0, math.inf), (-1.0, 1.0))}, "domain of a must be finite"),
        ({"domain": ((1.0, -1.0), (-1.0, 1.0))}, "domain of a must be finite with low < high"),
        ({"matrix": {(2, 0): 1.0}}, r"control_matrix entry \(2, 0\) is out of range"),
        ({"matrix": {(0, 1): 1.0}}, r"control_matrix entry \(0, 1\) is out of range"),
        ({"margin_shape": (2, 2)}, r"failure_margin_columns must return one value per state.*\(2, 2\)"),
        ({"horizon": float("nan")}, "horizon must be positive and finite"),
        ({"control_bounds": (-1.0, 1.0)}, "control_bounds must be a Box"),
        ({"periodic": (True, False)}, r"periodic dimension a must span \[-pi, pi\)"),
    ],
)
def test_bad_definitions_fail_at_construction_naming_the_field(changes, message):
    _Base()  # the good one builds
    with pytest.raises(ValueError, match=message):
        _Base(**changes)


# ---------------------------------------------------------------------- derived physics
@pytest.mark.parametrize("system", [DubinsAvoid(), DubinsAccel()], ids=lambda s: s.name)
def test_hamiltonian_and_optimal_inputs_match_brute_force_over_the_box_corners(system):
    """Several controls, a disturbance entering several states: H and u*, d* from the declared
    physics equal max_u min_d p . f over every corner of the input boxes."""
    gen = torch.Generator().manual_seed(1)
    x = system.sample_states(64, gen, dtype=torch.float64)
    p = torch.randn(64, system.state_dim, generator=gen, dtype=torch.float64)

    def corners(box):
        return [torch.tensor(c, dtype=torch.float64) for c in itertools.product(*zip(box.low, box.high))]

    best = torch.full((64,), -math.inf, dtype=torch.float64)
    for u in corners(system.control_bounds):
        worst = torch.full((64,), math.inf, dtype=torch.float64)
        for d in corners(system.disturbance_bounds):
            value = (p * system.dynamics(x, u.expand(64, -1), d.expand(64, -1))).sum(-1)
            worst = torch.minimum(worst, value)
        best = torch.maximum(best, worst)
    torch.testing.assert_close(system.hamiltonian(x, p), best)
    u, d = system.optimal_control(x, p), system.optimal_disturbance(x, p)
    torch.testing.assert_close((p * system.dynamics(x, u, d)).sum(-1), best)
    assert system.margin_rate_estimate() > 0


# ---------------------------------------------------------------------- the tutorial's path, toy size
def test_user_system_through_grid_training_verification_filter_and_sweep(tmp_path):
    from groundtruth import SolverSettings, solve
    from groundtruth.solution import GridSolution
    from safety import SafetyFilter, load_value_function
    from safety.verification.verify import VerifySettings, sample_states, verify
    from studies.filter_study import run_filter_study
    from studies.sweeps import SweepSpec, run_sweep
    from training import TrainConfig, Trainer

    # grid: by import path, saved and reloaded
    solution = solve(
        "my_systems:DubinsAvoid", 21, [0.0, 0.5, 1.0], settings=SolverSettings(compile=False), progress=False
    )
    solution.save(tmp_path / "gt.npz")
    assert GridSolution.load(tmp_path / "gt.npz").system == DubinsAvoid()
    brt = float((solution.values[-1] <= 0).float().mean())
    assert float((solution.values[0] <= 0).float().mean()) < brt < 1.0  # the tube grows and stays bounded

    # training: an instance in the config, stored as its import path
    system = DubinsAvoid()
    Trainer(TrainConfig(system=system, steps=20, **TINY), tmp_path / "run", progress=False).train()
    stored = json.loads((tmp_path / "run" / "config.json").read_text())
    assert stored["system"] == "my_systems:DubinsAvoid"
    loaded = load_value_function(tmp_path / "run", system="my_systems:DubinsAvoid").value_function
    assert loaded.system == system

    # verification by rollouts
    states = sample_states(system, 200, 0)
    row = verify(loaded, states, VerifySettings(samples=200, scenario_samples=0, robust_samples=0), progress=False)
    assert 0.0 <= row["violation_rate"] <= 1.0 and row["samples"] == 200

    # a filter on the grid: never passes the nominal input inside the BRT
    grid_vf = load_value_function(tmp_path / "gt.npz").value_function
    inside = torch.tensor([[0.3, -0.3, math.pi / 2]])  # heading into the disc, just below it
    u, info = SafetyFilter(grid_vf, 0.0)(inside, torch.tensor(1.0), torch.zeros(1, 1))
    assert bool(info.intervened[0])

    # filter evaluation with the default task (keep the nominal input) and a user policy
    study = run_filter_study(
        _scene(system),
        [("grid", grid_vf)],
        tmp_path / "fe.csv",
        episodes=40,
        kinds=("switch", "smooth"),
    )
    nominal, *filtered = study.rows
    assert math.isnan(nominal["goal_rate"])  # no goal for a system without one
    assert nominal["collision_rate"] > 0 and all(r["collision_rate"] <= nominal["collision_rate"] for r in filtered)
    turn_left = run_filter_study(
        _scene(system), [], tmp_path / "left.csv", episodes=10, nominal=lambda s: np.ones((len(s), 1))
    )
    assert turn_left.rows[0]["episodes"] == 10

    # a sweep of one layout and one seed, scored against the grid
    spec = SweepSpec(
        system=system,
        layouts=["ssl"],
        seeds=[0],
        budget_s=None,
        steps=10,
        snapshots=1,
        width=16,
        groundtruth=str(tmp_path / "gt.npz"),
        train={"points": 128},
    )
    report, failed = run_sweep(spec, tmp_path / "sweep", progress=False, log=lambda *_: None)
    assert not failed and report.exists()


def _scene(system):
    from reach_envs.scenes import system_scene

    return system_scene(system)


def test_cli_and_a_fresh_process_reload_a_user_system_run(tmp_path):
    """`reach groundtruth/train/evaluate/filter-eval` with --system pkg.module:Class, then the run
    reloads in a new process that names the system (and fails, naming the path, when it does not)."""
    gt, run = tmp_path / "gt.npz", tmp_path / "run"
    assert main(["groundtruth", "my_systems:DubinsAccel", "--grid", "9", "--times", "0,0.5", "--out", str(gt)]) == 0
    assert (
        main(
            [
                "train",
                "--system",
                "my_systems:DubinsAccel",
                "--steps",
                "10",
                "--width",
                "16",
                "--points",
                "128",
                "--out",
                str(run),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "filter-eval",
                str(gt),
                "--system",
                "my_systems:DubinsAccel",
                "--episodes",
                "8",
                "--time-to-go",
                "0.5",
                "--nominal",
                "numpy:zeros_like",
                "--out",
                str(tmp_path / "fe.csv"),
            ]
        )
        == 2
    )  # shape (N, n)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(EXAMPLES), os.environ.get("PYTHONPATH", "")])}
    base = [
        sys.executable,
        "-m",
        "reach",
        "evaluate",
        str(run),
        "--samples",
        "50",
        "--scenario-samples",
        "0",
        "--robust-samples",
        "0",
        "--out",
        str(tmp_path / "ev.csv"),
    ]
    refused = subprocess.run(base, env=env, capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2 and "my_systems:DubinsAccel" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    done = subprocess.run(
        [*base, "--system", "my_systems:DubinsAccel"], env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert "dubinsaccel" in (tmp_path / "ev.json").read_text().lower()
    assert my_systems.DubinsAccel  # the module stays importable here too


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--scene", "air3d", "--system", "my_systems:DubinsAvoid"], "not both"),
        (["--system", "my_systems:NoSuchSystem"], "has no 'NoSuchSystem'"),
        (["--system", "my_systems:DubinsAvoid", "--nominal", "math:pi"], "--nominal 'math:pi' is not callable"),
        (["--system", "my_systems:DubinsAvoid", "--nominal", "no_such_module_xyz:f"], "cannot import module"),
        (["--system", "my_systems:DubinsAvoid", "--nominal", "cruise"], "looks like 'package.module:Name'"),
    ],
)
def test_filter_eval_refuses_bad_system_and_nominal_options_before_work(options, message, tmp_path, capsys):
    out = tmp_path / "fe.csv"
    assert main(["filter-eval", "--episodes", "4", *options, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_hamiltonian_at_prunes_zero_columns_and_folds_single_entry_inputs():
    """A drift column written ``0.0 * x[k]`` costs the grid nothing once pruned, and an input that
    moves one state component with a number gain becomes one ``|p_i|`` coefficient."""
    system = DubinsAccel()
    x = TORCH.unbind(system.sample_states(8, generator=torch.Generator().manual_seed(0), dtype=torch.float64))
    pruned = system.hamiltonian_at(x, TORCH, prune=True)
    assert pruned.linear[2] is None and pruned.linear[3] is None  # heading and speed have no drift
    assert pruned.switches == []  # every input drives one component with a number gain
    assert pruned.absolute == pytest.approx([-system.wind, -system.wind, system.max_turn_rate, system.max_accel])
    assert system.hamiltonian_at(x, TORCH).linear[2] is not None  # unpruned: kept, as per call it must be
