"""Scenes: validation, named scenes, and proof that only the requested effects are computed."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import reach_envs  # noqa: F401
from reach.systems import Air3D, MultiVehicle9D
from reach_envs.env import ReachEnv
from reach_envs.policies import PursuitPolicy
from reach_envs.scenes import SCENES, Car, FixedState, Scene, make_scene


def _bit_state(env):
    return env.unwrapped.np_random.bit_generator.state


def _run(env, steps=30):
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        if terminated or truncated:
            break


def test_no_random_numbers_without_noise_or_random_policy():
    env = gym.make("Air3D-v0")  # pursuit disturbance is deterministic
    env.reset(seed=0)
    before = _bit_state(env)
    _run(env)
    assert _bit_state(env) == before
    assert env.unwrapped.sim.calls["process_noise"] == 0
    noisy = gym.make("Air3D-v0", process_noise=0.05)
    noisy.reset(seed=0)
    before = _bit_state(noisy)
    _run(noisy)
    assert _bit_state(noisy) != before and noisy.unwrapped.sim.calls["process_noise"] > 0


def test_no_disturbance_policy_call_without_a_disturbance(monkeypatch):
    calls = []
    original = PursuitPolicy.columns

    def spy(self, *args, **kwargs):
        calls.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(PursuitPolicy, "columns", spy)
    env = gym.make("Air3D-v0", disturbance=None)
    env.reset(seed=0)
    _run(env, 20)
    assert calls == [] and env.unwrapped.sim.calls["disturbance_policy"] == 0
    env = gym.make("Air3D-v0")
    env.reset(seed=0)
    _run(env, 20)
    assert len(calls) == env.unwrapped.sim.calls["disturbance_policy"] > 0


def test_no_figure_without_render_mode(created_figures):
    created = created_figures
    env = gym.make("Air3D-v0", scene="head-on")  # a scene with trails on
    env.reset(seed=0)
    _run(env)
    assert created == [] and env.unwrapped._renderer is None and env.unwrapped._trails == []
    env = gym.make("Air3D-v0", scene="head-on", render_mode="rgb_array")
    env.reset(seed=0)
    env.render()
    assert len(created) == 1


def test_no_arena_check_without_arena():
    env = gym.make("Air3D-v0")
    env.reset(seed=0)
    _run(env, 10)
    assert env.unwrapped.sim.calls["arena"] == 0
    env = gym.make("Air3D-v0", scene="crossing")
    env.reset(seed=0)
    _run(env, 10)
    assert env.unwrapped.sim.calls["arena"] == 10


def test_leaving_the_arena_terminates():
    env = gym.make("Air3D-v0", scene="head-on", arena=0.85)
    env.reset(options={"state": [-0.8, 0.0, 0.8, 0.0, math.pi, 0.0]})  # both cars drive outward
    terminated = False
    for _ in range(20):
        _, _, terminated, _, info = env.step(np.zeros(2, dtype=np.float32))
        if terminated:
            break
    assert terminated and info["out_of_arena"] and not info["collision"]


@pytest.mark.parametrize("name", sorted(SCENES))
def test_named_scenes_run(name):
    scene = make_scene(name)
    env = ReachEnv(scene)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (scene.system.state_dim,)
    _run(env, 5)


def test_scene_collisions_happen_in_the_collision_scenes():
    for name in ("head-on", "crossing", "three-car-merge", "three-car-crossing"):
        env = ReachEnv(name)
        env.reset(seed=0)
        collided = False
        for _ in range(env.scene.max_steps):
            _, _, terminated, truncated, info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
            collided |= info["collision"]
            if terminated or truncated:
                break
        assert collided, name


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: Scene.from_cars([Car(0.0, 1.0), Car(1.0, 1.0)]), "speed"),
        (lambda: Scene.from_cars([Car(1.0, 1.0), Car(1.0, 1.0)], collision_radius=0.0), "collision_radius"),
        (lambda: Scene.from_cars([Car(1.0, 1.0), Car(1.0, 1.0, role="ghost")]), "role"),
        (lambda: Scene.from_cars([]), "cars"),
        (lambda: Scene(Air3D(), dt=0.0), "dt"),
        (lambda: Scene(Air3D(), dt=5.0), "dt"),
        (lambda: Scene(Air3D(), horizon=-1.0), "horizon"),
        (lambda: Scene(Air3D(), integrator="rk45"), "integrator"),
        (lambda: Scene(Air3D(), process_noise=[0.1, 0.1]), "process_noise"),
        (lambda: Scene(Air3D(), process_noise=-0.1), "process_noise"),
        (lambda: Scene(Air3D(), disturbance="chase"), "disturbance"),
        (lambda: Scene(MultiVehicle9D(), disturbance="pursue"), "disturbance"),
        (lambda: Scene(Air3D(), arena=0.0), "arena"),
        (lambda: Scene(Air3D(), initial_state=[0.1, 0.2]), "initial_state"),
        (lambda: make_scene("air3d", speed=1.0), "unknown field"),
        (lambda: make_scene("nowhere"), "unknown scene"),
    ],
)
def test_invalid_scenes_fail_at_construction_naming_the_field(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_fixed_state_with_jitter_and_fixed_initial_state():
    scene = make_scene("air3d", initial_state=FixedState((0.5, 0.5, 0.0), jitter=0.01))
    env = ReachEnv(scene)
    obs, _ = env.reset(seed=0)
    assert np.allclose(obs, [0.5, 0.5, 0.0], atol=0.011) and not np.allclose(obs, [0.5, 0.5, 0.0], atol=1e-6)
    env = ReachEnv("air3d", initial_state=(0.5, -0.5, 4.0))  # headings are wrapped
    obs, _ = env.reset(seed=0)
    assert obs[2] == pytest.approx(4.0 - 2 * math.pi)


def test_uniform_safe_initial_states_are_outside_the_failure_set():
    env = gym.make("MultiVehicle9D-v0")
    for seed in range(50):
        _, info = env.reset(seed=seed)
        assert info["margin"] > 0


def test_pursuit_targets_the_nearest_control_car_on_every_backend():
    from reach.systems import FLOAT, NUMPY

    system = Scene.from_cars([Car(0.5, 1.0, "control"), Car(0.5, 1.0, "control"), Car(0.5, 2.0, "disturbance")]).system
    policy = PursuitPolicy(system)
    rng = np.random.default_rng(0)
    states = system.sample_states_numpy(rng, 64)
    batch = policy.columns(NUMPY.unbind(states), NUMPY, rng)[0]
    single = [policy.columns(s.tolist(), FLOAT, rng)[0] for s in states]
    np.testing.assert_allclose(batch, single, rtol=0, atol=1e-12)
    # pursuer at the origin heading +x, nearest control car straight above: turn left at full rate
    x = [0.0, 0.5, 0.0, -0.9, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert policy.columns(x, FLOAT, rng)[0] == 2.0
