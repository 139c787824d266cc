"""Environments of reach and reach-avoid systems (issue 41, point 5): goal and obstacles from the
margins, success and failure termination with ``info["outcome"]``, rewards, rendering, vector env."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import reach_envs
from reach.systems import FLOAT, NUMPY
from reach.systems.dubins import Dubins3D, DubinsReachAvoid
from reach_envs import make_env, make_vector_env
from reach_envs.parallel import MultiVehicleParallelEnv
from reach_envs.policies import MarginPursuit
from reach_envs.projection import FAILURE_RGB, GOAL_RGB, OBSTACLE_RGB
from reach_envs.regions import OUTCOME_REWARDS
from reach_envs.scenes import Scene, UniformSafe

# As in test_envs.py: positions are unbounded on purpose (cars drive off the sampling domain).
JUSTIFIED = ("A Box observation space minimum value is -infinity", "A Box observation space maximum value is infinity")
ZERO = np.zeros(1, dtype=np.float32)


def _check(env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    unexpected = [str(w.message) for w in caught if not any(j in str(w.message) for j in JUSTIFIED)]
    assert unexpected == []


def _episode(env, state, action=ZERO):
    """Reset to ``state`` and step ``action`` until the episode ends: ``(steps, reward, te, tr, info)``."""
    env.reset(seed=0, options={"state": state})
    for steps in range(1, 10_000):
        _, reward, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return steps, reward, terminated, truncated, info
        assert reward == 0.0 and info.get("outcome") is None
    raise AssertionError("the episode never ended")


def _pixels(frame, rgb):
    return int((np.abs(frame.astype(np.int64) - rgb).sum(axis=-1) <= 6).sum())


# ---------------------------------------------------------------------- API conformance and ids
@pytest.mark.parametrize(
    "make",
    [
        lambda: gym.make("DubinsReachAvoid-v0").unwrapped,
        lambda: gym.make("Reach-v0", system="dubins3d").unwrapped,
    ],
    ids=["DubinsReachAvoid-v0", "dubins3d-reach"],
)
def test_check_env_passes_for_reach_kinds(make):
    _check(make())


def test_ids_build_the_builtin_systems_in_each_mode():
    env = gym.make("DubinsReachAvoid-v0").unwrapped
    assert isinstance(env.system, DubinsReachAvoid) and env.scene.kind == "reach-avoid"
    assert env.scene.disturbance == "pursue" and "DubinsReachAvoid-v0" in reach_envs.SYSTEM_ENVS
    assert "DubinsReachAvoid-v0" not in reach_envs.ENV_SCENES  # no shipped value network for it
    reach = gym.make("Reach-v0", system="dubins3d").unwrapped
    assert reach.system.kind == "reach"
    avoid = gym.make("Reach-v0", system=Dubins3D(set_mode="avoid")).unwrapped
    _, info = avoid.reset(seed=0)
    assert set(info) == {"margin", "collision", "time"}  # an avoid env, keys as ever
    steps, reward, terminated, _, info = _episode(avoid, [-0.6, 0.0, 0.0])  # straight into the disc
    assert terminated and reward == -1.0 and info["collision"] and "outcome" not in info


# ---------------------------------------------------------------------- the scene's sets
def test_scene_derives_goal_and_obstacles_from_the_margins():
    system = DubinsReachAvoid()
    scene = Scene(system)
    x = [[0.7, 0.1, -1.0], [0.7, 0.0, 0.0]]
    columns = NUMPY.unbind(np.array([[0.7, 0.0, 0.0], [0.1, 0.1, 1.0], [-0.8, 0.5, 2.0]]))
    assert scene.goal.contains(columns, NUMPY).tolist() == [True, False, False]
    assert scene.obstacles.contains(columns, NUMPY).tolist() == [False, True, False]
    assert [r.name for r in scene.regions] == ["goal", "obstacles"]
    assert scene.goal.contains(x[0], FLOAT) and not scene.obstacles.contains(x[1], FLOAT)
    reach = Scene(Dubins3D())
    assert reach.obstacles is None and [r.name for r in reach.regions] == ["goal"]
    avoid = Scene(Dubins3D(set_mode="avoid"))
    assert avoid.goal is None and avoid.obstacles is None and [r.name for r in avoid.regions] == ["failure set"]


def test_initial_states_are_neither_in_the_goal_nor_in_an_obstacle():
    system = DubinsReachAvoid()
    rng = np.random.default_rng(0)
    states = np.array([UniformSafe().sample(system, rng) for _ in range(200)])
    columns = NUMPY.unbind(states)
    assert (system.target_margin_columns(columns, NUMPY) > 0).all()
    assert (system.constraint_margin_columns(columns, NUMPY) > 0).all()


@pytest.mark.parametrize("system", [DubinsReachAvoid(), Dubins3D()], ids=["reach-avoid", "reach"])
def test_scene_refuses_collisions_that_do_not_end_the_episode(system):
    with pytest.raises(ValueError, match=rf"terminate_on_collision must be True for a {system.kind} system"):
        Scene(system, terminate_on_collision=False)
    with pytest.raises(ValueError, match="terminate_on_collision"):
        make_env(system, terminate_on_collision=0)


def test_parallel_env_refuses_a_reach_kind_naming_it():
    with pytest.raises(ValueError, match="dubinsreachavoid is a reach-avoid problem"):
        MultiVehicleParallelEnv(Scene(DubinsReachAvoid()))


# ---------------------------------------------------------------------- outcomes and rewards
def test_steered_into_the_goal_terminates_reached_with_reward_one():
    env = gym.make("DubinsReachAvoid-v0")  # against the pursuing wind
    steps, reward, terminated, truncated, info = _episode(env, [0.4, 0.0, 0.0])  # goal 0.1 ahead
    assert terminated and not truncated and reward == 1.0 == OUTCOME_REWARDS["reached"]
    assert info["outcome"] == "reached" and info["reached"] and not info["collision"]
    assert info["target_margin"] <= 0.0 < info["constraint_margin"] == info["margin"]
    assert 8 <= steps <= 12  # 0.1 at 0.6 - 0.1 (the wind blows back): ~0.2 s
    assert info["disturbance"].tolist() == [-0.1, 0.0]  # the wind pushes away from the goal


def test_started_in_the_goal_terminates_on_the_first_step():
    env = make_env(Dubins3D())  # reach: the disc of radius 0.25 at the origin
    _, info = env.reset(options={"state": [0.0, 0.0, 0.0]})
    assert info["outcome"] is None and info["reached"] and info["target_margin"] == pytest.approx(-0.25)
    assert info["constraint_margin"] == math.inf and not info["collision"]
    steps, reward, terminated, _, info = _episode(env, [0.0, 0.0, 0.0])
    assert (steps, reward, terminated, info["outcome"]) == (1, 1.0, True, "reached")


def test_steered_into_the_obstacle_terminates_collided_with_reward_minus_one():
    env = gym.make("DubinsReachAvoid-v0")
    steps, reward, terminated, truncated, info = _episode(env, [-0.5, 0.0, 0.0])  # obstacle 0.35 ahead
    assert terminated and not truncated and reward == -1.0 == OUTCOME_REWARDS["collided"]
    assert info["outcome"] == "collided" and info["collision"] and not info["reached"]
    assert info["constraint_margin"] <= 0.0 and 10 <= steps <= 40
    with pytest.raises(reach_envs.spaces.EpisodeOverError):
        env.step(ZERO)


def test_a_state_in_goal_and_obstacle_counts_as_a_collision():
    system = DubinsReachAvoid(goal=(0.1, 0.0), goal_radius=0.3)  # the goal covers the obstacle
    env = make_env(system)
    steps, reward, _, _, info = _episode(env, [0.1, 0.0, 0.0])
    assert (steps, reward, info["outcome"], info["reached"]) == (1, -1.0, "collided", False)
    assert info["target_margin"] < 0 and info["constraint_margin"] < 0


def test_running_out_of_time_is_reported_as_a_timeout():
    env = make_env(Dubins3D(), horizon=0.2)  # heading away from the goal disc at the origin
    steps, reward, terminated, truncated, info = _episode(env, [0.8, 0.8, math.pi / 4])
    assert (steps, reward, terminated, truncated) == (10, 0.0, False, True)
    assert info["outcome"] == "timeout" and not info["reached"] and info["time"] == pytest.approx(0.2)


def test_pursuit_goes_for_the_nearer_win_of_the_disturbance():
    system = DubinsReachAvoid()
    policy = MarginPursuit(system)
    rng = np.random.default_rng(0)
    # nearer the goal (l <= g): blow away from it; nearer the obstacle: blow into it
    assert policy.columns([0.55, 0.1, 0.0], FLOAT, rng) == [-0.1, 0.1]
    assert policy.columns([-0.3, 0.2, 0.0], FLOAT, rng) == [0.1, -0.1]
    states = system.sample_states_numpy(rng, 32)
    batch = np.stack(policy.columns(NUMPY.unbind(states), NUMPY, rng), axis=-1)
    np.testing.assert_array_equal(batch, [policy.columns(s.tolist(), FLOAT, rng) for s in states])


# ---------------------------------------------------------------------- fail closed
@pytest.mark.parametrize("margin", ["target_margin_columns", "constraint_margin_columns"])
def test_a_non_finite_margin_raises_naming_the_state(margin):
    env = make_env(DubinsReachAvoid())
    env.reset(seed=0)
    setattr(env.system, margin, lambda x, xp: x[0] * math.nan)  # after construction's own checks
    with pytest.raises(ValueError, match=r"margin is NaN or infinite at state"):
        env.step(ZERO)
    venv = make_vector_env(DubinsReachAvoid(), 3)
    setattr(venv.system, margin, lambda x, xp: np.where(x[0] > 0.0, math.nan, 0.5))  # NaN in one row
    with pytest.raises(ValueError, match=r"margin is NaN or infinite at state \[0\.5, 0\.0, 0\.0\]"):
        venv.reset(options={"state": [[-0.5, 0.5, 0.0], [0.5, 0.0, 0.0], [-0.5, -0.5, 0.0]]})


# ---------------------------------------------------------------------- vector env
def test_vector_env_ends_each_episode_by_its_own_outcome_and_autoresets():
    venv = gym.make_vec("DubinsReachAvoid-v0", num_envs=3, vectorization_mode="vector_entry_point")
    states = [[0.48, 0.0, 0.0], [-0.2, 0.0, 0.0], [-0.9, 0.9, 2.4]]  # goal, obstacle, neither
    obs, info = venv.reset(seed=0, options={"state": states})
    assert info["outcome"].tolist() == [None] * 3 and info["target_margin"].shape == (3,)
    seen = {0: None, 1: None}
    for _ in range(20):
        _, reward, terminated, truncated, info = venv.step(np.zeros((3, 1), dtype=np.float32))
        for i in seen:
            if terminated[i]:
                seen[i] = (info["outcome"][i], reward[i])
        assert not (terminated[2] or truncated[2]) and info["outcome"][2] is None
        if all(seen.values()):
            break
    assert seen == {0: ("reached", 1.0), 1: ("collided", -1.0)}
    done = terminated.copy()
    obs, reward, terminated, truncated, info = venv.step(np.zeros((3, 1), dtype=np.float32))  # NEXT_STEP reset
    assert (reward[done] == 0).all() and not terminated[done].any() and not truncated[done].any()
    assert all(o is None for o in info["outcome"][done])
    columns = NUMPY.unbind(venv.unwrapped.state[done])
    assert (venv.unwrapped.system.target_margin_columns(columns, NUMPY) > 0).all()  # fresh, undecided states


@pytest.mark.parametrize(
    ("system", "fields"),
    [(Dubins3D(), {}), (DubinsReachAvoid(), {"disturbance": "pursue"})],
    ids=["reach", "reach-avoid"],
)
def test_vector_env_matches_single_envs_step_for_step(system, fields, lockstep):
    n = 4
    venv = make_vector_env(system, n, horizon=0.5, **fields)
    singles = [make_env(system, horizon=0.5, **fields) for _ in range(n)]
    obs, _ = venv.reset(seed=3)
    np.testing.assert_array_equal(obs, np.stack([env.reset(seed=3 + i)[0] for i, env in enumerate(singles)]))

    def outcomes_are_known(info):
        assert set(info["outcome"]) <= {None, "reached", "collided", "timeout"}

    assert lockstep(venv, singles, 60, 1.0, outcomes_are_known) > 0


def test_vector_env_times_out_with_an_outcome():
    venv = make_vector_env(Dubins3D(), 2, horizon=0.1)
    venv.reset(seed=0, options={"state": [[0.8, 0.8, 0.8], [-0.8, -0.8, -2.4]]})
    for _ in range(5):
        _, reward, terminated, truncated, info = venv.step(np.zeros((2, 1), dtype=np.float32))
    assert truncated.all() and not terminated.any() and info["outcome"].tolist() == ["timeout"] * 2
    assert reward.tolist() == [0.0, 0.0]


# ---------------------------------------------------------------------- rendering
def test_rendering_shades_the_goal_and_the_obstacles():
    env = gym.make("DubinsReachAvoid-v0", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (400, 400, 3) and frame.dtype == np.uint8
    goal, obstacle = _pixels(frame, GOAL_RGB), _pixels(frame, OBSTACLE_RGB)
    assert goal > 500 and obstacle > goal  # the obstacle disc (r=0.25) is larger than the goal (r=0.2)
    reach = make_env(Dubins3D(), render_mode="rgb_array")
    reach.reset(seed=0)
    frame = reach.render()
    assert _pixels(frame, GOAL_RGB) > 500 and _pixels(frame, FAILURE_RGB) == 0
    avoid = make_env(Dubins3D(set_mode="avoid"), render_mode="rgb_array")
    avoid.reset(seed=0)
    frame = avoid.render()
    assert _pixels(frame, GOAL_RGB) == 0 and _pixels(frame, FAILURE_RGB) > 500


def test_vector_env_renders_one_frame_per_sub_env():
    venv = make_vector_env(DubinsReachAvoid(), 2, render_mode="rgb_array")
    venv.reset(seed=0)
    frames = venv.render()
    assert len(frames) == 2 and all(_pixels(f, GOAL_RGB) > 0 for f in frames)
