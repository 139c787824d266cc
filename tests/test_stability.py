"""Hard cases stay numerically stable: rollouts, integrators, precision, chattering, extreme inputs.

The systems, solver and training suites hold their own hard cases (angles at +-pi and 1e3 rad,
coinciding cars, zero and subnormal costates, CFL, diverging training, NaN checkpoints); these
cover the closed loop.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from reach.systems import Air3D, MultiVehicle9D
from safety import SafetyFilter, rollout
from training import Encoding, NeuralValueFunction, ValueNetwork


def _tiny(system, seed=0, **kw):
    torch.manual_seed(seed)
    return NeuralValueFunction(ValueNetwork(system, "ssrsl", width=16, **kw))


def test_long_horizon_and_large_steps_keep_states_finite():
    system = MultiVehicle9D()
    vf = _tiny(system)
    x = system.sample_states(100, generator=torch.Generator().manual_seed(0))
    # 100x the default horizon (bang-bang inputs all the way), and a step 200x DeepReach's; the
    # network is built for that horizon, since networks refuse times-to-go beyond their own
    long = rollout(_tiny(MultiVehicle9D(horizon=100.0)), x, horizon=100.0, dt=0.05, record=True, progress=False)
    assert torch.isfinite(long.trajectories).all()
    for integrator in ("euler", "rk4"):
        coarse = rollout(vf, x, dt=0.5, integrator=integrator, record=True, progress=False)
        assert torch.isfinite(coarse.trajectories).all()
        assert (coarse.trajectories[..., 6:].abs() <= math.pi).all()  # headings stay wrapped


def test_zero_gradient_value_gives_tie_break_not_nan():
    class Flat:
        system = Air3D()

        def value(self, x, t):
            return torch.ones(x.shape[:-1], dtype=x.dtype)

        def gradient(self, x, t):
            return torch.zeros_like(x)

    x = Air3D().sample_states(50, generator=torch.Generator().manual_seed(0))
    r = rollout(Flat(), x, dt=0.01, record=True, progress=False)
    assert torch.isfinite(r.trajectories).all()
    # u* = d* = 0 (box centres): the relative heading never changes
    assert torch.allclose(r.trajectories[-1, :, 2], x[:, 2], atol=1e-6) or r.collided.any()
    u, info = SafetyFilter(Flat(), threshold=2.0, policy="gradient")(x, 1.0, torch.zeros(50, 1))
    assert info.intervened.all() and (u == 0).all()
    # the greedy input (the switch's default) on a flat V: scored by l where l < V, finite, in the box
    u, info = SafetyFilter(Flat(), threshold=2.0)(x, 1.0, torch.zeros(50, 1))
    box = Air3D().control_bounds
    assert info.intervened.all() and torch.isfinite(u).all()
    assert ((u >= box.low[0]) & (u <= box.high[0])).all()


def test_euler_and_rk4_agree_away_from_the_boundary(air3d_grid):
    x = Air3D().sample_states(1500, generator=torch.Generator().manual_seed(1))
    v = air3d_grid.value(x, 1.1)
    clear = v.abs() > 0.1
    euler = rollout(air3d_grid, x, integrator="euler", progress=False)
    rk4 = rollout(air3d_grid, x, integrator="rk4", progress=False)
    agree = (euler.collided == rk4.collided)[clear].float().mean()
    assert agree > 0.995
    # and the two converge as dt shrinks: disagreement over all states does not grow
    coarse = (
        (
            rollout(air3d_grid, x, dt=0.02, progress=False).collided
            != rollout(air3d_grid, x, dt=0.02, integrator="rk4", progress=False).collided
        )
        .float()
        .mean()
    )
    fine = (euler.collided != rk4.collided).float().mean()
    assert fine <= coarse + 1e-3


def test_float32_and_float64_rollouts_agree_away_from_the_boundary(air3d_grid):
    x = Air3D().sample_states(1500, generator=torch.Generator().manual_seed(2))
    clear = air3d_grid.value(x, 1.1).abs() > 0.1
    single = rollout(air3d_grid, x, dtype=torch.float32, progress=False)
    double = rollout(air3d_grid, x.double(), dtype=torch.float64, progress=False)
    assert ((single.collided == double.collided)[clear]).float().mean() > 0.995


@pytest.mark.parametrize("w0", [30.0, 200.0])
def test_sine_network_gradients_stay_finite_for_extreme_inputs(w0):
    system = MultiVehicle9D()
    vf = _tiny(system, w0=w0, encoding=Encoding.for_system(system, sincos=True))
    x = torch.tensor([[1e3, -1e3, 0.0, 0.0, 1e4, 1e4, 1e3, -1e3, math.pi]], dtype=torch.float32)
    v, g = vf.value_and_gradient(x, 1.0)
    assert torch.isfinite(v).all() and torch.isfinite(g).all()


def test_bad_states_into_filter_and_rollout_are_named():
    vf = _tiny(Air3D())
    bad = torch.tensor([[0.5, 0.5, float("nan")], [0.1, 0.2, 0.3]])
    with pytest.raises(ValueError, match="NaN or inf"):
        SafetyFilter(vf)(bad, 1.0, torch.zeros(2, 1))
    with pytest.raises(ValueError, match="NaN or inf"):
        rollout(vf, bad, progress=False)
    with pytest.raises(ValueError, match=r"states must have shape \(N, 3\)"):
        rollout(vf, torch.zeros(2, 2, 3), progress=False)
    with pytest.raises(ValueError, match="record=True"):
        rollout(vf, torch.zeros(200_000, 3), record=True, progress=False)
    assert np.isfinite(vf.value(torch.tensor([[1e6, -1e6, 1e6]]), 1.0).numpy()).all()


def test_values_and_gradients_agree_for_headings_two_pi_apart(air3d_grid):
    system = MultiVehicle9D()
    x = system.sample_states(200, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    for shift in (2 * math.pi, -4 * math.pi, 2 * math.pi * 160):  # up to about 1e3 rad
        y = x.clone()
        y[:, 6:] += shift
        for vf in (_tiny(system), _tiny(system, encoding=Encoding.for_system(system, sincos=True))):
            vf.network.double()
            assert torch.allclose(vf.value(x, 1.0), vf.value(y, 1.0), atol=1e-9)
            assert torch.allclose(vf.gradient(x, 1.0), vf.gradient(y, 1.0), atol=1e-8)
    a = Air3D().sample_states(200, generator=torch.Generator().manual_seed(4))
    b = a.clone()
    b[:, 2] -= 2 * math.pi
    assert torch.allclose(air3d_grid.value(a, 1.0), air3d_grid.value(b, 1.0), atol=1e-5)
    assert torch.allclose(air3d_grid.gradient(a, 1.0), air3d_grid.gradient(b, 1.0), atol=1e-4)


def test_nearest_pair_switch_is_continuous_with_finite_gradient():
    system = MultiVehicle9D()
    # car 1 at the origin, cars 2 and 3 both 0.5 away: the nearest pair is a tie
    x = torch.tensor([[0.0, 0.0, 0.5, 0.0, -0.5, 0.0, 0.0, 1.0, 2.0]], dtype=torch.float64, requires_grad=True)
    margin = system.failure_margin(x)
    (g,) = torch.autograd.grad(margin.sum(), x)
    assert margin.item() == pytest.approx(0.25) and torch.isfinite(g).all()
    eps = torch.zeros(1, 9, dtype=torch.float64)
    eps[0, 2] = 1e-9  # nudging car 2 moves the margin by at most the nudge: continuous across the kink
    assert abs(system.failure_margin(x.detach() + eps).item() - margin.item()) <= 1e-9 + 1e-15
    r = rollout(_tiny(system), x.detach().float(), dt=0.01, record=True, progress=False)
    assert torch.isfinite(r.trajectories).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tiny_and_subnormal_costates_never_give_nan(dtype):
    system = Air3D()
    tiny = torch.finfo(dtype).tiny
    sub = tiny / 2**10  # subnormal
    x = torch.tensor([[0.0, 0.0, 0.5]] * 4, dtype=dtype)
    p = torch.tensor([[0, 0, 1e-30], [0, 0, -sub], [0, 0, 0.0], [0, 0, -0.0]], dtype=dtype)
    u, d = system.optimal_control(x, p), system.optimal_disturbance(x, p)
    assert torch.isfinite(u).all() and torch.isfinite(d).all()
    # a nonzero costate, however small, picks its corner; exactly zero (either sign) the box centre
    assert u[:, 0].tolist() == [-3.0, 3.0, 0.0, 0.0] and d[:, 0].tolist() == [-3.0, 3.0, 0.0, 0.0]
    assert torch.isfinite(system.hamiltonian(x, p)).all()


def test_huge_finite_states_in_envs_stay_finite():
    import gymnasium as gym

    import reach_envs  # noqa: F401  (registers the ids; training no longer imports the env package)

    env = gym.make("MultiVehicle9D-v0")
    env.reset(seed=0, options={"state": [1e12, -1e12, 0.0, 0.0, 5e11, 5e11, 1e6, -1e6, 3.0]})
    obs, *_ = env.step(np.zeros(3, dtype=np.float32))
    assert np.isfinite(obs).all() and (np.abs(obs[6:]) <= math.pi).all()
