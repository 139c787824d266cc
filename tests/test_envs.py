"""Gymnasium environments: API conformance, dynamics, termination, inputs, vector env equivalence."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import reach_envs
from reach.systems import FLOAT, Air3D

ENV_IDS = list(reach_envs.ENV_SCENES)

# Observation boxes leave positions unbounded on purpose: cars drive off the sampling domain and
# process noise is unbounded, so any finite bound would be a lie. Gymnasium's checker warns about
# infinite bounds; these are the only warnings we accept.
JUSTIFIED = ("A Box observation space minimum value is -infinity", "A Box observation space maximum value is infinity")


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_check_env_passes_without_unjustified_warnings(env_id):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.make(env_id).unwrapped)
    unexpected = [str(w.message) for w in caught if not any(j in str(w.message) for j in JUSTIFIED)]
    assert unexpected == []


def test_done_when_command_prints_a_step():
    code = (
        "import gymnasium as gym, reach_envs; e = gym.make('Air3D-v0'); e.reset(seed=0); "
        "print(e.step(e.action_space.sample()))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "array(" in out and "'margin'" in out


def test_make_with_module_prefix_without_import():
    code = "import gymnasium as gym; e = gym.make('reach_envs:MultiVehicle9D-v0'); print(e.reset(seed=1)[0].shape)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "(9,)"


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_observations_are_float32_wrapped_and_in_space(env_id):
    env = gym.make(env_id)
    obs, info = env.reset(seed=3)
    system = env.unwrapped.system
    for _ in range(200):
        assert obs.dtype == np.float32 and env.observation_space.contains(obs)
        headings = obs[list(system.periodic_dims)]
        assert np.all(headings >= -np.float32(math.pi)) and np.all(headings < np.float32(math.pi) + 1e-6)
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert info["margin"] == pytest.approx(system.failure_margin_float(env.unwrapped.state.tolist()))
        if terminated or truncated:
            obs, info = env.reset()


def test_truncation_at_horizon_and_time():
    env = gym.make("Air3D-v0", terminate_on_collision=False, disturbance=None)
    env.reset(seed=0)
    steps = 0
    truncated = False
    while not truncated:
        _, _, terminated, truncated, info = env.step(np.zeros(1, dtype=np.float32))
        steps += 1
        assert not terminated
    assert steps == 55  # ceil(1.1 / 0.02)
    assert info["time"] == pytest.approx(1.1)


def test_collision_terminates_with_reward_and_info():
    env = gym.make("Air3D-v0")
    # pursuer just outside the radius, straight ahead of the evader, heading at it
    obs, info = env.reset(options={"state": [0.3, 0.0, math.pi]})
    assert info["margin"] == pytest.approx(0.05)
    obs, reward, terminated, truncated, info = env.step(np.zeros(1, dtype=np.float32))
    obs, reward, terminated, truncated, info = env.step(np.zeros(1, dtype=np.float32))
    assert info["collision"] and terminated and not truncated and reward == -1.0
    assert info["margin"] <= 0


def test_applied_inputs_are_reported_and_actions_clipped():
    env = gym.make("Air3D-v0", disturbance=None)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0.5], dtype=np.float32))
    assert info["control"].tolist() == [1.5] and info["disturbance"].tolist() == [0.0]
    _, _, _, _, info = env.step(np.array([7.0]))
    assert info["control"].tolist() == [3.0]
    _, _, _, _, info = env.step(np.array([-2.0]))
    assert info["control"].tolist() == [-3.0]


@pytest.mark.parametrize("bad", [np.array([np.nan]), np.array([np.inf]), np.array([0.1, 0.2]), np.float32(0.3), "x"])
def test_bad_actions_raise_value_error_naming_the_value(bad):
    env = gym.make("Air3D-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.unwrapped.step(bad)


def test_bad_reset_state_raises():
    env = gym.make("Air3D-v0")
    with pytest.raises(ValueError, match="non-finite"):
        env.reset(options={"state": [0.1, np.nan, 0.0]})
    with pytest.raises(ValueError, match="shape"):
        env.reset(options={"state": [0.1, 0.2]})


def test_env_step_follows_system_dynamics_with_rk4_and_euler():
    system = Air3D()
    x0 = np.array([0.6, -0.3, 1.0])
    ref = x0.copy()  # fine Euler reference over one 0.02 s step
    for _ in range(20000):
        ref = ref + 1e-6 * np.array(system.xdot_columns(ref.tolist(), [1.2], [0.0], FLOAT))
    results = {}
    for integrator in ("rk4", "euler"):
        env = gym.make("Air3D-v0", disturbance=None, integrator=integrator).unwrapped
        env.reset(options={"state": x0})
        env.step(np.array([0.4]))
        results[integrator] = np.abs(env.state - ref).max()
    assert results["rk4"] < 1e-7 < results["euler"] < 1e-3


def test_disturbance_options():
    seen = []

    def policy(state):
        seen.append(state.copy())
        return np.array([1.0])

    env = gym.make("Air3D-v0", disturbance=policy)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(1))
    assert info["disturbance"].tolist() == [1.0] and len(seen) == 1 and seen[0].shape == (3,)
    env = gym.make("Air3D-v0", disturbance="random")
    env.reset(seed=0)
    ds = [env.step(np.zeros(1))[4]["disturbance"][0] for _ in range(20)]
    assert all(-3 <= d <= 3 for d in ds) and len(set(ds)) == 20
    env = gym.make("Air3D-v0", disturbance=lambda s: np.array([np.nan]))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.zeros(1))
    # pursuit: a pursuer to the left of its heading's line of sight turns toward the evader
    env = gym.make("Air3D-v0")
    env.reset(options={"state": [0.0, 0.8, 0.0]})  # pursuer above the evader, heading +x: must turn right
    assert env.step(np.zeros(1))[4]["disturbance"][0] < 0


def test_seeded_episodes_are_reproducible():
    def run(seed):
        env = gym.make("MultiVehicle6D-v0")
        env.action_space.seed(seed)
        obs, _ = env.reset(seed=seed)
        out = [obs]
        for _ in range(40):
            obs, *_ = env.step(env.action_space.sample())
            out.append(obs)
        return np.array(out)

    assert np.array_equal(run(4), run(4)) and not np.array_equal(run(4), run(5))


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_vector_env_matches_single_envs_step_for_step(env_id, lockstep):
    n = 5
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point")
    assert type(venv).__name__ == "ReachVectorEnv"
    singles = [gym.make(env_id) for _ in range(n)]
    obs, _ = venv.reset(seed=11)
    single_obs = np.stack([env.reset(seed=11 + i)[0] for i, env in enumerate(singles)])
    np.testing.assert_array_equal(obs, single_obs)
    resets = lockstep(venv, singles, 150, 1.3)
    assert resets > 0


def test_vector_env_unseeded_reset_continues_the_stream():
    def initial_states():
        venv = gym.make_vec("Air3D-v0", num_envs=3, vectorization_mode="vector_entry_point")
        first, _ = venv.reset(seed=5)
        second, _ = venv.reset()
        return first, second

    (a1, a2), (b1, b2) = initial_states(), initial_states()
    np.testing.assert_array_equal(a1, b1)
    np.testing.assert_array_equal(a2, b2)  # reproducible after one seeded reset
    assert not np.array_equal(a1, a2)
    single = gym.make("Air3D-v0")
    single.reset(seed=6)
    np.testing.assert_array_equal(single.reset()[0], a2[1])  # sub-env 1 continues like a single env


def test_vector_env_shapes_and_bad_actions():
    venv = gym.make_vec("MultiVehicle9D-v0", num_envs=3, vectorization_mode="vector_entry_point")
    obs, info = venv.reset(seed=0)
    assert obs.shape == (3, 9) and obs.dtype == np.float32 and info["margin"].shape == (3,)
    obs, rew, te, tr, info = venv.step(np.zeros((3, 3), dtype=np.float32))
    assert rew.shape == te.shape == tr.shape == (3,) and info["control"].shape == (3, 3)
    with pytest.raises(ValueError, match="shape"):
        venv.step(np.zeros((3, 2)))
    bad = np.zeros((3, 3))
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        venv.step(bad)
