"""A policy that decides every control period and holds its input in between (RolloutSettings.control_period)."""

from __future__ import annotations

import pytest
import torch

from reach.integrators import make_stepper
from reach.systems.arrays import TORCH
from safety.value_loading import load_value_function
from safety.verification.rollout import RolloutSettings, rollout
from safety.verification.verify import VerifySettings


@pytest.fixture(scope="module")
def air3d():
    return load_value_function("pretrained:air3d").value_function


def _states(vf, n: int = 64) -> torch.Tensor:
    x = vf.system.sample_states(4 * n, generator=torch.Generator().manual_seed(3))
    safe = vf.value(x, 0.3) > 0.2  # far from the failure set for the short horizon below
    return x[safe][:n]


@pytest.mark.parametrize("policy", ["gradient", "greedy"])
def test_a_period_of_one_step_is_deciding_at_every_step(air3d, policy):
    x = _states(air3d, 32)
    every = rollout(air3d, x, horizon=0.3, dt=0.01, policy=policy, record=True)
    held = rollout(air3d, x, horizon=0.3, dt=0.01, policy=policy, record=True, control_period=0.01)
    assert torch.equal(every.trajectories, held.trajectories)


def test_the_held_gradient_policy_is_u_star_decided_every_period_with_d_star_every_step(air3d):
    x = _states(air3d)
    dt, period, steps = 0.01, 0.04, 30
    result = rollout(air3d, x, horizon=steps * dt, dt=dt, record=True, control_period=period)
    system = air3d.system
    advance = make_stepper(system, dt, "euler", TORCH)
    y = x.clone()
    for k in range(steps):
        t = steps * dt - k * dt
        p = air3d.gradient(y, t)
        if k % 4 == 0:
            u = system.optimal_control(y, p)
        d = system.optimal_disturbance(y, p)
        cols = advance(TORCH.unbind(y), system.input_columns(u, system.control_bounds, "u"),
                       system.input_columns(d, system.disturbance_bounds, "d"))  # fmt: skip
        y = TORCH.stack(cols, like=cols[0])
        assert torch.allclose(result.trajectories[k + 1], y, atol=1e-6), k
    assert not bool(result.collided.any())
    every = rollout(air3d, x, horizon=steps * dt, dt=dt, record=True)
    assert not torch.allclose(every.trajectories[-1], y, atol=1e-4)  # holding made a difference


@pytest.mark.parametrize("period", [0.015, -0.02, float("nan"), 0.0])
def test_a_period_that_is_not_a_whole_number_of_steps_is_refused_naming_it(period):
    with pytest.raises(ValueError, match="control_period"):
        RolloutSettings(dt=0.01, control_period=period)
    with pytest.raises(ValueError, match="control_period"):
        VerifySettings(dt=0.01, control_period=period)


def test_verification_rolls_out_the_held_policy(air3d):
    settings = VerifySettings(dt=0.01, control_period=0.05, policy="greedy")
    assert settings.rollout_settings(0.5).control_period == 0.05
    assert settings.to_dict()["control_period"] == 0.05
