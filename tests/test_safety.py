"""Safety: the filter's exactness and its guarantee with a grid value, rollouts, metrics, wrappers."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import reach_envs  # noqa: F401 - registers the envs
from reach.systems import Air3D, MultiVehicle9D
from reach_envs.parallel import parallel_env
from reach_envs.vector import ReachVectorEnv
from safety import (
    GreedyPolicy,
    OptimalPolicy,
    SafetyFilter,
    SafetyFilterParallelWrapper,
    SafetyFilterVectorWrapper,
    SafetyFilterWrapper,
    rollout,
    scenario_epsilon,
    violation_statistics,
    wilson_interval,
)
from safety.verification.verify import sample_superlevel_set
from training import Encoding, NeuralValueFunction, ValueNetwork


def tiny_network(system, layout="ssrsl", seed=0, **kw) -> NeuralValueFunction:
    torch.manual_seed(seed)
    return NeuralValueFunction(ValueNetwork(system, layout, width=16, **kw))


# ---------------------------------------------------------------------- fused value and gradient
@settings(max_examples=20, deadline=None)
@given(
    layout=st.text(alphabet="srt", min_size=1, max_size=4).map(lambda s: s + "l"),
    parameterisation=st.sampled_from(["exact", "vanilla"]),
    sincos=st.booleans(),
    nine=st.booleans(),
)
def test_fused_gradient_equals_autograd(layout, parameterisation, sincos, nine):
    system = MultiVehicle9D() if nine else Air3D()
    torch.manual_seed(1)
    net = ValueNetwork(
        system, layout, width=32, parameterisation=parameterisation, encoding=Encoding.for_system(system, sincos=sincos)
    ).double()
    vf = NeuralValueFunction(net)
    x = system.sample_states(64, dtype=torch.float64)
    t = torch.rand(64, dtype=torch.float64) * system.horizon
    v, g = vf.value_and_gradient(x, t)
    assert torch.allclose(v, vf.value(x, t), atol=1e-12)
    assert torch.allclose(g, vf.autograd_gradient(x, t), atol=1e-10)


# ---------------------------------------------------------------------- filter
@pytest.mark.parametrize("policy", ["gradient", "greedy", None])
def test_filter_keeps_nominal_or_applies_its_backup_input_exactly(policy):
    """The switch keeps the nominal input bit for bit or applies its backup input: u* (gradient) or
    the greedy policy's input (greedy, the switch's default)."""
    system = MultiVehicle9D()
    vf = tiny_network(system)
    x = system.sample_states(512, generator=torch.Generator().manual_seed(0))
    t = system.horizon
    v = vf.value(x, t)
    threshold = float(v.median())
    nominal = torch.rand(512, 3, generator=torch.Generator().manual_seed(1)) * 2.2 - 1.1
    u, info = SafetyFilter(vf, threshold, policy=policy)(x, t, nominal)
    active = v <= threshold
    if policy == "gradient":
        backup = OptimalPolicy(vf).control(x[active], t)
    else:
        backup = GreedyPolicy(vf, integrator="rk4").control(x[active], t)
    assert 0 < int(active.sum()) < 512
    assert torch.equal(info.intervened, active)
    assert torch.equal(u[active], backup)
    assert torch.equal(u[~active], nominal[~active])
    assert torch.equal(info.applied, u) and torch.equal(info.nominal, nominal)


def test_filter_rejects_bad_input():
    system = Air3D()
    f = SafetyFilter(tiny_network(system), 0.0)
    x = torch.zeros(4, 3) + 0.5
    with pytest.raises(ValueError, match="NaN or inf"):
        f(torch.tensor([[0.5, float("nan"), 0.0]]), 1.0, torch.zeros(1, 1))
    with pytest.raises(ValueError, match="u_nominal contains NaN"):
        f(x, 1.0, torch.full((4, 1), float("inf")))
    with pytest.raises(ValueError, match=r"u_nominal must have shape \(4, 1\)"):
        f(x, 1.0, torch.zeros(4, 2))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        f(torch.zeros(4, 9), 1.0, torch.zeros(4, 1))
    with pytest.raises(ValueError, match="threshold"):
        SafetyFilter(tiny_network(system), float("nan"))


def _run_vector(env, actions_fn, steps):
    n = env.num_envs
    collided = np.zeros(n, bool)
    alive = np.ones(n, bool)
    interventions = 0
    for _ in range(steps):
        _, _, term, trunc, info = env.step(actions_fn(n))
        collided |= info["collision"] & alive
        interventions += int(np.sum(info.get("filter_intervened", np.zeros(n, bool)) & alive))
        alive &= ~(term | trunc)
    return collided, interventions


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_filter_prevents_collisions_against_worst_case_pursuer(air3d_grid, seed):
    sol = air3d_grid
    policy = OptimalPolicy(sol)
    horizon = sol.system.horizon

    def pursuer(x):  # the worst-case disturbance of the same value function
        return policy.disturbance(torch.as_tensor(x), horizon).numpy()

    n = 600
    straight = lambda k: np.zeros((k, 1), np.float32)  # noqa: E731 - nominal evader ignores the pursuer
    nominal_env = ReachVectorEnv(n, "air3d", disturbance=pursuer)
    nominal_env.reset(seed=seed)
    start = torch.as_tensor(nominal_env.state)
    outside = (sol.value(start, horizon) > 0.1).numpy()
    nominal, _ = _run_vector(nominal_env, straight, nominal_env.scene.max_steps)

    filtered_env = SafetyFilterVectorWrapper(ReachVectorEnv(n, "air3d", disturbance=pursuer), sol)
    filtered_env.reset(seed=seed)
    assert np.array_equal(filtered_env.unwrapped.state, start.numpy())
    filtered, interventions = _run_vector(filtered_env, straight, nominal_env.scene.max_steps)
    assert outside.sum() > 400
    assert nominal[outside].sum() > 20  # unfiltered, the attacked evader does crash
    assert filtered[outside].sum() == 0  # filtered, never from outside the BRT
    assert interventions > 0


def test_gym_wrapper_is_exact_and_rebuilds_from_spec(air3d_grid, tmp_path):
    path = tmp_path / "air3d.npz"
    air3d_grid.save(path)
    env = SafetyFilterWrapper(gym.make("Air3D-v0"), str(path), threshold=0.05)
    rebuilt = gym.make(env.spec)
    assert isinstance(rebuilt, SafetyFilterWrapper) and rebuilt.safety_filter.threshold == 0.05
    for e in (env, rebuilt):
        e.reset(seed=3)
    kept = replaced = 0
    for k in range(40):
        action = np.array([math.sin(k)], dtype=np.float32)
        _, _, term, trunc, info = env.step(action)
        _, _, _, _, info2 = rebuilt.step(action)
        assert info["filter_value"] == pytest.approx(info2["filter_value"])
        if info["filter_intervened"]:
            replaced += 1
            assert abs(float(info["applied_action"][0])) in (0.0, 1.0)
        else:
            kept += 1
            assert np.array_equal(info["applied_action"], action)
        assert info["nominal_action"] is not None
        if term or trunc:
            break
    assert kept > 0
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([float("nan")], dtype=np.float32))


def test_wrapper_refuses_value_function_of_another_system(air3d_grid):
    with pytest.raises(ValueError, match="environment simulates"):
        SafetyFilterWrapper(gym.make("MultiVehicle9D-v0"), air3d_grid)


def test_parallel_wrapper_matches_vector_wrapper():
    system = MultiVehicle9D()
    vf = tiny_network(system, seed=4)
    par = SafetyFilterParallelWrapper(parallel_env("three-car-9d"), vf, threshold=0.3)
    vec = SafetyFilterVectorWrapper(ReachVectorEnv(1, "three-car-9d", terminate_on_collision=False), vf, threshold=0.3)
    obs, _ = par.reset(seed=0)
    vec.unwrapped.reset(seed=0, options={"state": par.unwrapped.full_state[None]})
    v0 = float(vf.value(torch.as_tensor(par.unwrapped.full_state), system.horizon))
    par.safety_filter.threshold = vec.safety_filter.threshold = v0 + 0.01  # filter from the first step on
    interventions = 0
    for k in range(20):
        actions = {a: np.array([0.5 * math.cos(k + i)], dtype=np.float32) for i, a in enumerate(par.agents)}
        joint = np.array([[actions[a][0] for a in par.unwrapped.possible_agents]], dtype=np.float32)
        _, _, _, _, infos = par.step(actions)
        _, _, _, _, vinfo = vec.step(joint)
        for i, a in enumerate(par.unwrapped.possible_agents):
            assert infos[a]["applied_action"] == pytest.approx(float(vinfo["applied_action"][0, i]))
            assert infos[a]["filter_intervened"] == bool(vinfo["filter_intervened"][0])
        interventions += infos[par.unwrapped.possible_agents[0]]["filter_intervened"]
        assert np.allclose(par.unwrapped.full_state, vec.unwrapped.state[0], atol=1e-9)
        if not par.agents:
            break
    assert interventions > 0


# ---------------------------------------------------------------------- rollouts
def test_early_exit_changes_work_not_outcomes():
    system = MultiVehicle9D()
    vf = tiny_network(system, seed=2)
    x = system.sample_states(400, generator=torch.Generator().manual_seed(5))
    full = rollout(vf, x, early_exit=False, progress=False, dt=0.01)
    fast = rollout(vf, x, early_exit=True, progress=False, dt=0.01, chunk_size=128)
    assert torch.equal(full.collided, fast.collided)
    assert torch.allclose(full.collision_time, fast.collision_time, equal_nan=True)
    assert torch.equal(full.initial_value, fast.initial_value)
    assert fast.state_steps < full.state_steps
    assert (fast.decided_time <= system.horizon + 1e-9).all()
    # states in collision at t = 0 are decided before any step
    start_hit = system.failure_margin(x) <= 0
    assert start_hit.any() and (fast.collision_time[start_hit] == 0).all()


def test_the_heading_aware_floor_skips_more_than_the_speed_bound(monkeypatch):
    """The cars' margin floor decides more trajectories than the speed-only default floor, with the
    same outcome for every state."""
    from reach.systems.base import ControlAffineSystem
    from reach.systems.multivehicle import MultiVehicle

    system = MultiVehicle9D()
    vf = tiny_network(system, seed=2)
    x = system.sample_states(400, generator=torch.Generator().manual_seed(6))
    headings = rollout(vf, x, progress=False, dt=0.01)
    monkeypatch.setattr(MultiVehicle, "margin_floor", ControlAffineSystem.margin_floor)
    speed_only = rollout(vf, x, progress=False, dt=0.01)
    assert torch.equal(headings.collided, speed_only.collided)
    assert torch.allclose(headings.collision_time, speed_only.collision_time, equal_nan=True)
    assert headings.state_steps < 0.8 * speed_only.state_steps


def test_rollout_records_frozen_trajectories_and_matches_recorded_collisions():
    system = Air3D()
    vf = tiny_network(system, seed=3)
    x = system.sample_states(50, generator=torch.Generator().manual_seed(0))
    r = rollout(vf, x, dt=0.01, record=True, progress=False)
    traj = r.trajectories
    assert traj.shape == (111, 50, 3)
    margins = system.failure_margin(traj)
    assert torch.equal((margins <= 0).any(0), r.collided)
    assert (traj[:, :, 2] >= -math.pi).all() and (traj[:, :, 2] < math.pi).all()


def test_margin_rate_bound_holds():
    for system in (Air3D(), MultiVehicle9D()):
        x = system.sample_states(4000, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        gen = torch.Generator().manual_seed(1)
        u = (torch.rand(4000, system.control_dim, generator=gen, dtype=torch.float64) * 2 - 1) * torch.tensor(
            system.control_bounds.half_width, dtype=torch.float64
        )
        d = None
        if system.disturbance_dim:
            d = (torch.rand(4000, system.disturbance_dim, generator=gen, dtype=torch.float64) * 2 - 1) * torch.tensor(
                system.disturbance_bounds.half_width, dtype=torch.float64
            )
        xg = x.clone().requires_grad_(True)
        (dl,) = torch.autograd.grad(system.failure_margin(xg).sum(), xg)
        rate = (dl * system.dynamics(x, u, d)).sum(-1).abs()
        bound = system.margin_rate_bound()
        assert rate.max() <= bound + 1e-9
        assert rate.max() > 0.9 * bound  # and it is tight, not a loose guess


def test_rollout_rejects_bad_input():
    vf = tiny_network(Air3D())
    with pytest.raises(ValueError, match="NaN or inf"):
        rollout(vf, torch.tensor([[0.5, float("inf"), 0.0]]), progress=False)
    with pytest.raises(ValueError, match="dt"):
        rollout(vf, torch.zeros(2, 3) + 0.5, dt=-1.0, progress=False)
    with pytest.raises(ValueError, match="integrator"):
        rollout(vf, torch.zeros(2, 3) + 0.5, integrator="midpoint", progress=False)


def test_grid_rollouts_are_near_zero_false_safe(air3d_grid):
    x = air3d_grid.system.sample_states(3000, generator=torch.Generator().manual_seed(0))
    r = rollout(air3d_grid, x, progress=False)
    stats = violation_statistics(r.initial_value, r.collided)
    assert stats["false_safe_rate"] < 2e-3
    assert 0.05 < stats["collision_rate"] < 0.15


# ---------------------------------------------------------------------- metrics
def test_scenario_epsilon_matches_closed_form_and_lin_bansal():
    assert scenario_epsilon(0, 100_000, 1e-16) == pytest.approx(1 - 1e-16 ** (1 / 100_000), rel=1e-6)
    assert scenario_epsilon(0, 100_000, 1e-16) == pytest.approx(3.7e-4, rel=0.01)
    assert scenario_epsilon(731, 3_680_000, 1e-16) == pytest.approx(2.65e-4, rel=0.01)
    assert scenario_epsilon(10, 1000, 1e-3) > scenario_epsilon(5, 1000, 1e-3) > scenario_epsilon(5, 2000, 1e-3)
    with pytest.raises(ValueError):
        scenario_epsilon(5, 5)


@settings(max_examples=30, deadline=None)
@given(k=st.integers(0, 50), extra=st.integers(1, 5000))
def test_scenario_epsilon_is_the_binomial_tail_root(k, extra):
    n = k + extra
    eps = scenario_epsilon(k, n, 1e-6)
    # P(Bin(n, eps) <= k) = beta, computed independently with math.comb in exact rationals' floats
    tail = sum(math.comb(n, i) * eps**i * (1 - eps) ** (n - i) for i in range(k + 1))
    assert tail == pytest.approx(1e-6, rel=1e-4)


def test_violation_statistics_counts_each_kind():
    v = torch.tensor([0.5, 0.2, -0.1, -0.3, 0.4])
    collided = torch.tensor([True, False, False, True, False])
    s = violation_statistics(v, collided)
    assert s["false_safe_rate"] == pytest.approx(0.2)
    assert s["false_unsafe_rate"] == pytest.approx(0.2)
    assert s["violation_rate"] == pytest.approx(0.4)
    assert s["collision_rate"] == pytest.approx(0.4)
    assert s["delta"] == pytest.approx(0.5) and s["safe_fraction"] == 0.0
    lo, hi = wilson_interval(2, 5)
    assert lo < 0.4 < hi


def test_superlevel_sampling_stays_in_the_set(air3d_grid):
    x, draws = sample_superlevel_set(air3d_grid, 0.2, 500, seed=0, t=1.1)
    assert x.shape == (500, 3) and draws >= 500
    assert (air3d_grid.value(x, 1.1) > 0.2).all()
    with pytest.raises(ValueError, match="too small"):
        sample_superlevel_set(air3d_grid, 100.0, 10, seed=0, t=1.1, max_draws=100_000)


def test_bfloat16_matmuls_stay_close_to_float32_and_are_opt_in(air3d_grid):
    system = MultiVehicle9D()
    torch.manual_seed(1)
    vf = NeuralValueFunction(ValueNetwork(system, "ssrsl", width=64))
    x = system.sample_states(512, generator=torch.Generator().manual_seed(2))
    v, g = vf.value_and_gradient(x, 1.0)
    vb, gb = vf.with_matmul_dtype(torch.bfloat16).value_and_gradient(x, 1.0)
    assert vb.dtype == torch.float32 and gb.dtype == torch.float32
    assert 0 < (v - vb).abs().max() < 1e-2  # rounded, so not equal; small against V's O(1) range
    rel = (g - gb).norm(dim=-1) / g.norm(dim=-1)
    # typically 0.1 % (median 0.08 % here); states next to a ReLU kink can see a slope flip (the
    # 99th percentile is ~2 %), so the bound on the tail is on how many, not how far
    assert rel.median() < 3e-3 and (rel > 0.1).float().mean() < 0.01
    exact = rollout(vf, x[:256], progress=False, dt=0.01)
    fast = rollout(vf, x[:256], progress=False, dt=0.01, matmul_precision="bfloat16")
    assert torch.equal(exact.initial_value, fast.initial_value)  # V(x, T) itself stays float32
    assert (exact.collided == fast.collided).float().mean() >= 0.97
    with pytest.raises(ValueError, match="neural value function"):
        rollout(air3d_grid, torch.zeros(2, 3) + 0.5, progress=False, matmul_precision="bfloat16")
    with pytest.raises(ValueError, match="matmul_precision"):
        rollout(vf, x[:4], progress=False, matmul_precision="float16")
