"""Reach and reach-avoid problems through training, rollouts, verification and the results table.

The grid solver's side is in test_problem_kinds.py; here each downstream tool reads the kind from
the system: the residual is the kind's variational inequality, a rollout succeeds by reaching the
target, and verification bounds ``{V < -delta}``.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
import torch

from groundtruth import SolverSettings, solve
from reach.systems import Dubins3D, DubinsReachAvoid
from safety.verification.metrics import violation_statistics
from safety.verification.rollout import rollout
from safety.verification.rollout_store import RolloutStore
from safety.verification.verify import VerifySettings, sample_states, verify
from training import NeuralValueFunction, TrainConfig, Trainer, ValueNetwork
from training.loss import _residual, hji_residual, residual_function

SMALL = 31


@pytest.fixture(scope="module")
def reach_avoid_grid():
    """DubinsReachAvoid's value on a coarse grid, every 0.25 s to its 2 s horizon, read beyond its
    edge at the nearest node (rollouts may leave the domain and come back)."""
    grid = solve(
        DubinsReachAvoid(), SMALL, [0.25 * k for k in range(9)], settings=SolverSettings(compile=False), progress=False
    )
    grid.outside = "clamp"
    return grid


@pytest.mark.parametrize(
    "system, parameterisation",
    [
        (Dubins3D("reach"), "exact"),
        (Dubins3D("reach"), "vanilla"),
        (DubinsReachAvoid(), "exact"),
        (DubinsReachAvoid(), "exact-constraint"),
        (DubinsReachAvoid(), "vanilla"),
    ],
)
def test_the_fused_residual_of_each_kind_matches_autograd(system, parameterisation):
    torch.manual_seed(0)
    net = ValueNetwork(system, "sssl", 32, parameterisation)
    x = system.sample_states(128, torch.Generator().manual_seed(1))
    t = torch.rand(128, generator=torch.Generator().manual_seed(2)) * system.horizon
    r_auto, v_auto, g_auto = hji_residual(net, x, t, "autograd")
    r_fused, v_fused, g_fused = residual_function(net, "fused", compile=False)(x, t)
    torch.testing.assert_close(r_fused, r_auto, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(v_fused, v_auto, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(g_fused, g_auto, atol=2e-5, rtol=1e-4)
    # the inference pass agrees with the forward pass
    vf = NeuralValueFunction(net)
    v, g = vf.value_and_gradient(x, 0.7)
    torch.testing.assert_close(v, net(x, torch.full((128,), 0.7)), atol=1e-5, rtol=1e-5)


def test_the_exact_parameterisations_hold_the_boundary_and_the_constraint():
    system = DubinsReachAvoid()
    x = system.sample_states(4096, torch.Generator().manual_seed(0))
    boundary = torch.maximum(system.target_margin(x), -system.constraint_margin(x))
    torch.testing.assert_close(system.boundary_value(x), boundary)
    for parameterisation in ("exact", "exact-constraint"):
        net = ValueNetwork(system, "ssl", 16, parameterisation)
        with torch.no_grad():
            net.output.bias.fill_(-5.0)  # pull V far down: only a held constraint stops it
            torch.testing.assert_close(net(x, torch.zeros(4096)), boundary)
            v = net(x, torch.full((4096,), 2.0))
        below = bool((v < -system.constraint_margin(x) - 1e-6).any())
        assert below == (parameterisation == "exact")


def test_the_reach_avoid_residual_is_the_variational_inequality():
    """``min(max(dV/dt - H, V - l), V + g)``: zero where V = l in the target, zero where the obstacle
    term binds (V = -g), and negative where V dips below -g."""
    system = DubinsReachAvoid()
    net = ValueNetwork(system, "ssl", 8)
    x = torch.tensor([[0.7, 0.0, 0.0], [0.1, 0.0, 0.0], [0.1, 0.0, 0.0]])
    target, g = system.target_margin(x), system.constraint_margin(x)
    p = torch.zeros(3, 3)
    v = torch.stack([target[0], -g[1], -g[2] - 0.1])
    r = _residual(net, x, v, p, torch.zeros(3), target, g)
    assert abs(float(r[0])) < 1e-6 and abs(float(r[1])) < 1e-6
    assert float(r[2]) == pytest.approx(-0.1, abs=1e-6)


def test_bad_parameterisations_and_labels_fail_before_training(tmp_path):
    with pytest.raises(ValueError, match="'exact-constraint' holds a reach-avoid constraint; dubins3d is a reach"):
        TrainConfig(system=Dubins3D("reach"), parameterisation="exact-constraint", steps=1).validate()
    with pytest.raises(ValueError, match="parameterisation must be one of"):
        TrainConfig(system="dubinsreachavoid", parameterisation="exactly", steps=1).validate()
    config = TrainConfig(system=Dubins3D("reach"), lower_bound="policy", steps=1, layout="ssl", width=8, points=64)
    with pytest.raises(ValueError, match="lower_bound labels handle"):
        Trainer(config.validate(), tmp_path / "run", progress=False)


def test_a_reach_avoid_run_trains_and_reloads_in_a_new_process(tmp_path):
    config = TrainConfig(
        system="dubinsreachavoid",
        parameterisation="exact-constraint",
        layout="ssl",
        width=16,
        points=256,
        steps=20,
        compile=False,
        log_every=5,
    )
    summary = Trainer(config.validate(), tmp_path / "run", progress=False).train()
    assert summary["steps"] == 20
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert rows and all(math.isfinite(r["loss"]) for r in rows)
    code = (
        "import torch; from safety.value_loading import load_value_function;"
        f"vf = load_value_function({str(tmp_path / 'run')!r}).value_function;"
        "x = vf.system.sample_states(8);"
        "print(vf.system.kind, vf.network.parameterisation, bool(torch.isfinite(vf.value(x, 2.0)).all()))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["reach-avoid", "exact-constraint", "True"]


def test_a_reach_rollout_succeeds_by_reaching_the_target_and_fails_by_colliding(reach_avoid_grid):
    grid = reach_avoid_grid
    x = torch.tensor(
        [
            [0.7, 0.0, 0.0],  # in the goal: reached at once
            [0.1, 0.0, 0.0],  # in the obstacle: collided at once
            [0.4, 0.0, 0.0],  # facing the goal from 0.3 away: reached in about 0.17 s
            [-0.9, 0.9, 2.5],  # far, facing away: cannot reach in 2 s
        ]
    )
    r = rollout(grid, x, dt=0.01, progress=False)
    assert r.kind == "reach-avoid"
    assert r.reached.tolist() == [True, False, True, False]
    assert r.collided.tolist()[:2] == [False, True]
    assert r.failed.tolist() == [False, True, False, True]
    assert float(r.reach_time[0]) == 0.0 and 0.1 < float(r.reach_time[2]) < 0.3
    assert math.isnan(float(r.reach_time[3]))
    torch.testing.assert_close(r.oriented_value, -r.initial_value)
    assert bool((r.initial_value[[0, 2]] < 0).all()) and bool((r.initial_value[[1, 3]] > 0).all())


def test_statistics_of_a_reach_kind_count_violations_both_ways():
    v = torch.tensor([-0.5, -0.2, -0.1, 0.3, 0.4])  # V: the first three claim reachable
    failed = torch.tensor([False, True, False, False, True])
    row = violation_statistics(-v, failed, "reach-avoid", collided=torch.tensor([False, True, False, False, False]))
    assert row["false_reachable_rate"] == pytest.approx(1 / 5)  # V = -0.2 claimed, failed
    assert row["false_unreachable_rate"] == pytest.approx(1 / 5)  # V = 0.3 denied, succeeded
    assert row["failure_rate"] == pytest.approx(2 / 5) and row["collision_rate"] == pytest.approx(1 / 5)
    assert row["delta"] == pytest.approx(0.2)  # scenario set {V < -0.2}
    assert row["reachable_fraction"] == pytest.approx(1 / 5)
    assert "false_safe_rate" not in row and "safe_fraction" not in row
    with pytest.raises(ValueError, match="kind must be one of"):
        violation_statistics(v, failed, "escape")


def test_verification_bounds_the_reachable_set_below_minus_delta(reach_avoid_grid, tmp_path):
    grid = reach_avoid_grid
    settings = VerifySettings(samples=600, scenario_samples=200, robust_samples=0, dt=0.01)
    states = sample_states(grid.system, settings.samples, settings.seed)
    with RolloutStore(tmp_path / "store", {"test": 1}) as store:
        row = verify(grid, states, settings, progress=False, store=store)
        again = verify(grid, states, settings, progress=False, store=store)
        assert store.loaded_blocks > 0
    assert row["problem"] == "reach-avoid"
    for key in ("false_reachable_rate", "false_unreachable_rate", "failure_rate", "failure_ci_low"):
        assert key in row and key in again and row[key] == again[key]
    assert row["scenario_volume"] == row["reachable_fraction"] > 0
    assert row["scenario_states"] == 200
    # the scenario sample lies in {V < -delta}
    from safety.verification.verify import sample_superlevel_set

    fresh, _ = sample_superlevel_set(grid, row["delta"], 50, 1, 2.0)
    assert bool((grid.value(fresh, 2.0) < -row["delta"]).all())


def test_a_results_table_names_the_kind_and_refuses_to_mix_kinds(reach_avoid_grid, tmp_path):
    from studies.batch_verification import SourceLoading, evaluate_many, markdown_table

    path = tmp_path / "ra.npz"
    reach_avoid_grid.save(path)
    settings = VerifySettings(samples=300, scenario_samples=0, robust_samples=0, dt=0.01)
    rows = evaluate_many([str(path)], tmp_path / "table", settings, progress=False)
    assert rows[0]["problem"] == "reach-avoid" and "false_reachable_rate" in rows[0]
    table = markdown_table(rows)
    assert "false reachable %" in table and "false safe %" not in table and "mixes" not in table
    mixed = markdown_table([*rows, {"label": "air", "problem": "avoid", "false_safe_rate": 0.0}])
    assert mixed.startswith("This table mixes kinds of problem (avoid, reach-avoid)")
    avoid = solve(Dubins3D("avoid"), 21, [0.0, 1.0], settings=SolverSettings(compile=False), progress=False)
    avoid_path = tmp_path / "avoid.npz"
    avoid.save(avoid_path)
    rows = evaluate_many(
        [str(avoid_path)], tmp_path / "other", settings, loading=SourceLoading(system=Dubins3D("reach")), progress=False
    )
    assert "for a avoid problem (dubins3d), not a reach problem" in rows[0]["error"]


def test_robust_scenario_set_of_a_reach_kind_bounds_below_minus_the_level(reach_avoid_grid):
    grid = reach_avoid_grid
    settings = VerifySettings(samples=200, scenario_samples=0, robust_samples=3000, target_eps=0.1, beta=1e-3, dt=0.01)
    row = verify(grid, sample_states(grid.system, 200, 0), settings, progress=False)
    assert "robust_error" not in row, row.get("robust_error")
    level = row["robust_level"]
    assert math.isfinite(level) and row["robust_eps"] <= 1.0 and row["robust_scenario_volume"] > 0
    # the scenario set is {V < -level}: its volume is that share of a uniform sample
    x = sample_states(grid.system, 3000, settings.seed + 2)
    share = float((grid.value(x, 2.0) < -level).double().mean())
    assert row["robust_scenario_volume"] == pytest.approx(share, abs=1e-9)


def test_a_reach_problem_has_no_collisions_and_bounds_its_reachable_set():
    """A plain reach problem (DeepReach's Dubins3D, reach mode): nothing to collide with, success is
    reaching the disc in time, and the same verification bounds {V < -delta}."""
    grid = solve(Dubins3D("reach"), 21, [0.0, 0.5, 1.0], settings=SolverSettings(compile=False), progress=False)
    grid.outside = "clamp"
    x = torch.tensor([[0.5, 0.0, math.pi], [0.5, 0.0, 0.0], [0.0, 0.1, 0.0]])  # facing it, facing away, inside
    r = rollout(grid, x, dt=0.01, progress=False)
    assert r.kind == "reach" and not bool(r.collided.any())
    assert r.reached.tolist() == [True, False, True] and float(r.reach_time[2]) == 0.0
    settings = VerifySettings(samples=400, scenario_samples=100, robust_samples=0, dt=0.01)
    row = verify(grid, sample_states(grid.system, 400, 0), settings, progress=False)
    assert row["problem"] == "reach" and "collision_rate" not in row and row["scenario_states"] == 100
    assert row["failure_rate"] > 0 and row["scenario_volume"] == row["reachable_fraction"] > 0


@pytest.mark.parametrize("kind", ["reach", "reach-avoid"])
def test_the_target_floor_exit_changes_work_not_outcomes(kind, reach_avoid_grid):
    """A reach rollout stops a trajectory once its target is out of reach in the time left (a
    reach-avoid one only where its obstacle is too): the same successes, violations and times as
    simulating every step, from less work; the stopped ones are decided before the horizon."""
    if kind == "reach":
        grid = solve(Dubins3D("reach"), 21, [0.0, 0.5, 1.0], settings=SolverSettings(compile=False), progress=False)
        grid.outside = "clamp"
    else:
        grid = reach_avoid_grid
    x = sample_states(grid.system, 600, 4)
    full = rollout(grid, x, dt=0.01, early_exit=False, progress=False)
    fast = rollout(grid, x, dt=0.01, early_exit=True, progress=False, chunk_size=256)
    assert torch.equal(full.reached, fast.reached) and torch.equal(full.collided, fast.collided)
    assert full.reached.any() and (~full.reached).any() and (kind == "reach" or full.collided.any())
    torch.testing.assert_close(full.reach_time, fast.reach_time, equal_nan=True)
    torch.testing.assert_close(full.collision_time, fast.collision_time, equal_nan=True)
    assert fast.state_steps < 0.9 * full.state_steps
    stopped = fast.decided_time < full.decided_time
    assert stopped.any() and not (fast.reached | fast.collided)[stopped].any()


@pytest.mark.parametrize("avoid_only", [False, True], ids=["reach-avoid", "avoid"])
def test_narrow_passage_rollouts_stop_early_with_the_same_outcomes(avoid_only):
    """NarrowPassage declares how far its cars can move (target and clearance floors): its rollouts
    stop the trajectories whose goal (and, for reach-avoid, whose collision) is out of reach, with the
    same outcomes and times as simulating every step, from less work."""
    from reach.systems.deepreach_catalogue import NarrowPassage
    from training import NeuralValueFunction, ValueNetwork

    torch.manual_seed(0)
    vf = NeuralValueFunction(ValueNetwork(NarrowPassage(avoid_only=avoid_only), "ssssl", width=16))
    x = sample_states(vf.system, 400, 5)
    full = rollout(vf, x, dt=0.01, early_exit=False, progress=False)
    fast = rollout(vf, x, dt=0.01, early_exit=True, progress=False, chunk_size=128)
    assert torch.equal(full.collided, fast.collided)
    torch.testing.assert_close(full.collision_time, fast.collision_time, equal_nan=True)
    if not avoid_only:
        assert torch.equal(full.reached, fast.reached)
        torch.testing.assert_close(full.reach_time, fast.reach_time, equal_nan=True)
    assert full.collided.any() and (~full.collided).any()
    assert fast.state_steps < 0.9 * full.state_steps
