"""Fleet scenes, the batched fleet simulator and the fleet Gymnasium / PettingZoo environments."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st
from pettingzoo.test import parallel_api_test

import reach_envs
from reach.integrators import make_stepper
from reach.systems.arrays import TORCH
from reach_envs.fleet import FleetSimulator, goal_seeking, positions, rollout
from reach_envs.fleet_envs import FleetEnv, FleetParallelEnv
from reach_envs.fleet_render import render_fleet
from reach_envs.fleet_scenes import LAYOUTS, FleetScene
from reach_envs.rendering import CRASHED_COLOUR
from reach_envs.spaces import EpisodeOverError


def _pairwise(points: torch.Tensor) -> torch.Tensor:
    """Distances ``(B, N, N)`` with the diagonal at +inf."""
    d = torch.cdist(points, points, compute_mode="donot_use_mm_for_euclid_dist")
    return d + torch.diag(torch.full((points.shape[1],), math.inf, dtype=d.dtype))


# ---------------------------------------------------------------------- the environments' APIs
@pytest.mark.parametrize("env_id", list(reach_envs.FLEET_ENVS))
def test_check_env_passes_at_16_cars(env_id):
    env = gym.make(env_id, n_cars=16, render_mode="rgb_array")
    assert env.unwrapped.scene.layout == reach_envs.FLEET_ENVS[env_id] and env.unwrapped.scene.n_cars == 16
    check_env(env.unwrapped)
    assert env.observation_space.shape == (80,) and env.action_space.shape == (16,)


@pytest.mark.filterwarnings("ignore:unknown reset option")  # parallel_api_test resets with options={"options": 1}
@pytest.mark.parametrize("layout", LAYOUTS)
def test_parallel_api_test_passes_at_16_cars(layout):
    env = FleetParallelEnv(layout, n_cars=16)
    parallel_api_test(env, num_cycles=400)
    assert env.possible_agents == [f"car_{i}" for i in range(1, 17)]


# ---------------------------------------------------------------------- scenes
@settings(max_examples=40, deadline=None)
@given(st.sampled_from(LAYOUTS), st.integers(2, 64), st.integers(0, 2**31), st.sampled_from(["straight", "random"]))
def test_samples_are_separated_finite_and_reachable_within_the_horizon(layout, n, seed, exits):
    scene = FleetScene(layout, n, exits=exits)
    x, goals = scene.sample(3, seed)
    assert x.shape == (3, 3 * n) and goals.shape == (3, n, 2) and x.dtype == goals.dtype == torch.float64
    assert bool(torch.isfinite(x).all() and torch.isfinite(goals).all())
    th = x[:, 2 * n :]
    assert bool(((th >= -math.pi) & (th < math.pi)).all())
    slack = 0.0 if layout == "random-goals" else 2.0 * scene.jitter  # jittered layouts may close by that much
    assert float(_pairwise(positions(x, n)).min()) >= scene.min_separation - slack
    assert float(_pairwise(goals).min()) > 2.0 * scene.collision_radius  # no two goals share a spot
    straight = torch.linalg.vector_norm(goals - positions(x, n), dim=-1)
    assert float(straight.max()) <= scene.max_distance + 1e-9
    assert 2.0 * float(straight.max()) / min(scene.speeds) < scene.episode_horizon
    pos = torch.cat([positions(x, n), goals], dim=1)
    assert float(pos.abs().max()) <= scene.extent


@pytest.mark.parametrize("layout", LAYOUTS)
def test_the_same_seed_gives_the_same_episodes_and_another_seed_others(layout):
    scene = FleetScene(layout, 12, exits="random")
    a, b, c = scene.sample(4, 7), scene.sample(4, 7), scene.sample(4, 8)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0], c[0])
    seeded = FleetScene(layout, 12, seed=5)
    assert torch.equal(seeded.sample(2)[0], seeded.sample(2)[0])
    env = FleetEnv(layout, n_cars=12)
    o1, _ = env.reset(seed=3)
    actions = [env.action_space.sample() for _ in range(20)]
    run1 = [env.step(a)[0] for a in actions]
    o2, _ = env.reset(seed=3)
    run2 = [env.step(a)[0] for a in actions]
    assert np.array_equal(o1, o2) and all(np.array_equal(p, q) for p, q in zip(run1, run2))
    penv = FleetParallelEnv(layout, n_cars=12)
    assert np.array_equal(penv.reset(seed=3)[0]["car_1"], o1)


def test_circle_swap_starts_on_a_circle_heading_in_with_antipodal_goals():
    scene = FleetScene("circle-swap", 24)
    x, goals = scene.sample(2, 0)
    p = positions(x, 24)
    r = torch.linalg.vector_norm(p, dim=-1)
    assert float((r - scene.circle_radius).abs().max()) <= math.sqrt(2) * scene.jitter
    assert torch.allclose(goals, -p)
    inward = torch.atan2(-p[..., 1], -p[..., 0])
    assert float(TORCH.wrap_angle(x[:, 48:] - inward).abs().max()) <= scene.jitter + 1e-12


def test_intersection_cars_head_in_on_the_arms_and_exit_elsewhere():
    scene = FleetScene("intersection", 16, exits="random")
    x, goals = scene.sample(50, 1)
    p = positions(x, 16)
    on_x_axis = p[..., 1].abs() <= scene.collision_radius + 1e-9  # east/west arms
    on_y_axis = p[..., 0].abs() <= scene.collision_radius + 1e-9
    assert bool((on_x_axis ^ on_y_axis).all())
    heading = torch.stack([torch.cos(x[:, 32:]), torch.sin(x[:, 32:])], dim=-1)
    assert bool(((heading * p).sum(-1) < 0).all())  # every car heads in
    entry = torch.atan2(p[..., 1], p[..., 0]).div(math.pi / 2).round() % 4
    exit_ = torch.atan2(goals[..., 1], goals[..., 0]).div(math.pi / 2).round() % 4
    assert bool((entry != exit_).all())  # nobody turns back
    assert len(set((exit_ - entry).remainder(4).flatten().tolist())) == 3  # right, straight and left all occur


# ---------------------------------------------------------------------- the simulator
@pytest.mark.parametrize("speed", [0.6, (0.6, 0.4, 0.9, 0.6, 0.4, 0.6, 0.6)])
def test_grouped_stepping_equals_the_n_car_systems_own_step_exactly(speed):
    scene = FleetScene("random-goals", 7, speed=speed, max_turn_rate=(1.1, 1.1, 0.8, 1.1, 1.1, 1.1, 2.0))
    sim = FleetSimulator(scene)
    x, goals = scene.sample(5, 2)
    u = goal_seeking(x, goals, scene)
    present = torch.ones(5, 7, dtype=torch.bool)
    system = scene.system()
    reference = torch.stack(
        make_stepper(system, scene.dt, "rk4", TORCH)(list(x.unbind(-1)), list(u.unbind(-1)), []), -1
    )
    assert torch.equal(sim.advance(x, u, present), reference)
    assert system.num_cars == 7 and system.control_dim == 7


def test_collisions_and_arrivals_count_present_cars_only_and_absent_cars_stay_put():
    scene = FleetScene("random-goals", 3, goal_radius=0.2)
    sim = FleetSimulator(scene)
    # cars 1 and 2 overlap, car 3 overlaps car 1 but is absent; car 2's goal is where it ends up
    x = torch.tensor([[0.0, 0.0, 0.1, 0.0, 0.05, 0.05, 0.0, 0.0, 1.0]], dtype=torch.float64)
    goals = torch.tensor([[[5.0, 0.0], [0.13, 0.0], [0.05, 0.05]]], dtype=torch.float64)
    present = torch.tensor([[True, True, False]])
    u = torch.zeros(1, 3, dtype=torch.float64)
    x1, hit, arrived, after = sim.step(x, u, present, goals)
    assert hit.tolist() == [[True, True, False]]
    assert arrived.tolist() == [[False, False, False]]  # car 2 reached its goal in a collision: a collision
    assert after.tolist() == [[False, False, False]]
    assert torch.equal(x1[0, [4, 5, 8]], x[0, [4, 5, 8]])  # the absent car did not move
    far = torch.tensor([[0.0, 0.0, 3.0, 0.0, 6.0, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    goals = torch.tensor([[[0.03, 0.0], [9.0, 9.0], [0.0, 9.0]]], dtype=torch.float64)
    _, hit, arrived, after = sim.step(far, u, torch.ones(1, 3, dtype=torch.bool), goals)
    assert (
        not bool(hit.any()) and arrived.tolist() == [[True, False, False]] and after.tolist() == [[False, True, True]]
    )


def test_unfiltered_circle_swap_collides_at_the_centre():
    scene = FleetScene("circle-swap", 8)
    x, goals = scene.sample(6, 0)
    out = rollout(scene, x, goals, record=True)
    assert bool(out.any_collision.all())
    first = int((~out.present.all(dim=2)).any(dim=1).nonzero()[0])  # the step of the first departure
    crashed = ~out.present[first] & out.collided
    assert bool(crashed.any())
    where = positions(out.states[first], 8)[crashed]
    assert float(torch.linalg.vector_norm(where, dim=-1).max()) < 0.25 * scene.circle_radius


def test_goal_seeking_brings_most_cars_home_in_a_sparse_random_goals_scene():
    scene = FleetScene("random-goals", 4, density=0.005)
    x, goals = scene.sample(40, 0)
    out = rollout(scene, x, goals)
    clear = ~out.any_collision
    assert float(clear.double().mean()) >= 0.8
    assert bool(out.arrived[clear].all())  # every car of a collision-free episode arrived
    distance = torch.linalg.vector_norm(goals - positions(x, 4), dim=-1)
    assert bool((out.arrival_time[clear] >= (distance[clear] - scene.goal_radius) / 0.6 - 1e-9).all())
    assert float(out.goal_rate.mean()) >= 0.8


@settings(max_examples=30, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-math.pi, math.pi), st.floats(0.3, 6.0))
def test_a_lone_car_reaches_any_goal_even_inside_its_turning_circle(heading, bearing, distance):
    scene = FleetScene("random-goals", 2, horizon=40.0)
    goal = (distance * math.cos(bearing), distance * math.sin(bearing))
    x = torch.tensor([[0.0, 0.0, 500.0, 500.0, heading, 0.0]], dtype=torch.float64)
    goals = torch.tensor([[goal, (505.0, 500.0)]], dtype=torch.float64)
    out = rollout(scene, x, goals)
    r = 0.6 / 1.1
    bound = (distance + 2.0 * math.pi * r + 4.0 * r) / 0.6  # a full turn and a detour around the circle
    assert bool(out.arrived.all()) and float(out.arrival_time[0, 0]) <= bound


def test_goal_seeking_turns_toward_the_goal_within_the_bound():
    scene = FleetScene("random-goals", 2)
    x = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2]], dtype=torch.float64)
    goals = torch.tensor([[[0.0, 5.0], [5.0, 0.0]]], dtype=torch.float64)  # car 1: left; car 2: right
    u = goal_seeking(x, goals, scene)
    assert u.tolist() == [[1.1, -1.1]]
    ahead = torch.tensor([[[5.0, 0.0], [0.0, 5.0]]], dtype=torch.float64)
    assert goal_seeking(x, ahead, scene).abs().max() == 0.0


# ---------------------------------------------------------------------- the environments' episodes
def test_fleet_env_rewards_arrivals_and_collisions_and_ends_when_no_car_is_left():
    env = FleetEnv("random-goals", n_cars=3)
    state = [0.0, 0.0, 0.2, 0.0, 9.0, 0.0, 0.0, math.pi, 0.0]  # cars 1, 2 nose to nose; car 3 next to its goal
    goals = [[5.0, 5.0], [-5.0, 5.0], [9.05, 0.0]]
    obs, info = env.reset(options={"state": state, "goals": goals})
    assert np.allclose(obs, np.array(state + [c for g in goals for c in g], dtype=np.float32))
    _, reward, terminated, truncated, info = env.step(np.zeros(3, dtype=np.float32))
    assert info["collision"].tolist() == [True, True, False] and info["arrived"].tolist() == [False, False, True]
    assert reward == -1.0 and terminated and not truncated and info["present"].tolist() == [False] * 3
    with pytest.raises(EpisodeOverError):
        env.step(np.zeros(3, dtype=np.float32))


def test_fleet_env_truncates_at_the_horizon():
    env = FleetEnv("circle-swap", n_cars=2, horizon=0.2)
    env.reset(seed=0)
    ends = [env.step(np.zeros(2, dtype=np.float32))[3] for _ in range(env.scene.max_steps)]
    assert ends == [False] * (env.scene.max_steps - 1) + [True]


def test_a_parallel_agent_terminates_on_its_own_collision_or_arrival_only():
    env = FleetParallelEnv("random-goals", n_cars=3)
    state = [0.0, 0.0, 0.2, 0.0, 9.0, 0.0, 0.0, math.pi, math.pi / 2]
    env.reset(options={"state": state, "goals": [[5.0, 5.0], [-5.0, 5.0], [9.0, 8.0]]})
    _, rewards, terms, truncs, infos = env.step({a: np.zeros(1, dtype=np.float32) for a in env.agents})
    assert terms == {"car_1": True, "car_2": True, "car_3": False} and not any(truncs.values())
    assert rewards["car_1"] == -1.0 and rewards["car_3"] == 0.0 and infos["car_1"]["collision"]
    assert env.agents == ["car_3"] and infos["car_3"]["time"] == pytest.approx(env.scene.dt)
    for _ in range(400):
        _, rewards, terms, _, infos = env.step({"car_3": np.zeros(1, dtype=np.float32)})
        if not env.agents:
            break
    assert terms == {"car_3": True} and rewards == {"car_3": 1.0} and infos["car_3"]["arrived"]


def test_frames_show_the_fleet_and_crashed_cars_in_grey():
    scene = FleetScene("circle-swap", 4)
    x, goals = scene.sample(1, 0)
    present = torch.ones(4, dtype=torch.bool)
    frame = render_fleet(x[0], goals[0], present, scene, 0.0)
    assert frame.shape == (480, 480, 3) and frame.dtype == np.uint8
    grey = np.array([int(CRASHED_COLOUR[i : i + 2], 16) for i in (1, 3, 5)])
    crashed = render_fleet(x[0], goals[0], ~present, scene, 1.0, crashed=present)
    greys = [int((f == grey).all(-1).sum()) for f in (frame, crashed)]  # (anti-aliasing makes a few anyway)
    assert greys[1] > greys[0] + 100
    env = FleetEnv(scene, render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    env.step(np.ones(4, dtype=np.float32))
    assert first.shape == (480, 480, 3) and not np.array_equal(first, env.render())


# ---------------------------------------------------------------------- refusals
@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"layout": "roundabout"}, "layout"),
        ({"n_cars": 1}, "n_cars"),
        ({"n_cars": True}, "n_cars"),
        ({"speed": -0.6}, "speed"),
        ({"speed": (0.6, 0.6)}, "speed"),
        ({"max_turn_rate": float("nan")}, "max_turn_rate"),
        ({"dt": 0.0}, "dt"),
        ({"horizon": 0.01}, "horizon"),
        ({"separation": 0.2}, "separation"),
        ({"jitter": 0.5}, "jitter"),
        ({"exits": "u-turn"}, "exits"),
        ({"layout": "random-goals", "density": 2.0}, "density 2"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_scenes_are_refused_by_name(fields, match):
    with pytest.raises(ValueError, match=match):
        FleetScene(**{"n_cars": 4, **fields})


def test_bad_simulator_input_is_refused_by_name():
    scene = FleetScene("circle-swap", 4)
    sim = FleetSimulator(scene)
    x, goals = scene.sample(2, 0)
    present = torch.ones(2, 4, dtype=torch.bool)
    u = torch.zeros(2, 4, dtype=torch.float64)
    bad_x = x.clone()
    bad_x[1, 3] = math.nan
    bad_u = u.clone()
    bad_u[1, 2] = 1.2
    nan_u = u.clone()
    nan_u[0, 0] = math.inf
    for args, match in [
        ((bad_x, u, present, goals), "x contains a non-finite"),
        ((x[:, :5], u, present, goals), "x must have shape"),
        ((x, bad_u, present, goals), "turn rate 1.2 of car_3"),
        ((x, nan_u, present, goals), "u contains a non-finite"),
        ((x, u[:, :3], present, goals), "u must have shape"),
        ((x, u, present.double(), goals), "present must be a bool"),
        ((x, u, present, goals[:, :, :1]), "goals must have shape"),
        ((x.numpy(), u, present, goals), "x must be a torch tensor"),
    ]:
        with pytest.raises(ValueError, match=match):
            sim.step(*args)
    edge = torch.full((2, 4), 1.1 * (1 + 1e-12), dtype=torch.float64)
    assert float(sim.check_inputs(edge, 2).max()) == 1.1  # a solver's rounding is clamped, not refused
    with pytest.raises(ValueError, match="goals must have shape"):
        goal_seeking(x, goals[:1], scene)


def test_bad_env_input_is_refused_by_name():
    env = FleetEnv("intersection", n_cars=4)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([0.0, math.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="'state' and 'goals' go together"):
        env.reset(options={"state": np.zeros(12)})
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(options={"sate": np.zeros(12)})
    with pytest.raises(ValueError, match="state contains a non-finite"):
        env.reset(options={"state": [math.nan] * 12, "goals": np.zeros((4, 2))})
    with pytest.raises(ValueError, match="unknown FleetScene setting"):
        FleetEnv(n_car=4)
    with pytest.raises(ValueError, match="render_mode"):
        FleetEnv(render_mode="human")
    penv = FleetParallelEnv("intersection", n_cars=4)
    penv.reset(seed=0)
    with pytest.raises(ValueError, match="missing"):
        penv.step({"car_1": np.zeros(1)})
    with pytest.raises(ValueError, match="agent 'car_2'"):
        penv.step({a: np.array([math.nan] if a == "car_2" else [0.0]) for a in penv.agents})
    with pytest.raises(ValueError, match="present must have shape"):
        render_fleet(np.zeros(12), np.zeros((4, 2)), np.ones(3, dtype=bool), env.scene)
