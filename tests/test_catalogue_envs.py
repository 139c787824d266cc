"""Environments of DeepReach's catalogue and the N-car family (issue 42, point 2): a Gymnasium id per
system, PettingZoo envs for the multi-agent ones (the N-car scenes, NarrowPassage's two cars as a
team), and ``reach envs`` listing them all."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

import reach_envs
from reach.systems import Dubins3D, MultiVehicle12D, MultiVehicle15D, NarrowPassage, Quadrotor
from reach_cli import main
from reach_envs.agents import agent_inputs
from reach_envs.parallel import MultiVehicleParallelEnv, parallel_env
from reach_envs.scenes import SCENES, UniformSafe

# As in test_envs.py: non-periodic dimensions are unbounded on purpose (states leave the domain).
JUSTIFIED = ("A Box observation space minimum value is -infinity", "A Box observation space maximum value is infinity")
NEW_IDS = [
    "Dubins3D-v0",
    "NarrowPassage-v0",
    "Quadrotor-v0",
    "ParameterizedVertDrone2D-v0",
    "MultiVehicle12D-v0",
    "MultiVehicle15D-v0",
    "RocketLanding-v0",
    "ReachAvoidRocketLanding-v0",
]


@pytest.mark.parametrize("env_id", NEW_IDS)
def test_check_env_passes_for_each_new_id(env_id):
    assert env_id in reach_envs.SYSTEM_ENVS and env_id not in reach_envs.ENV_SCENES  # no shipped network
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.make(env_id).unwrapped, skip_render_check=True)
    assert [str(w.message) for w in caught if not any(j in str(w.message) for j in JUSTIFIED)] == []


@pytest.mark.parametrize(
    ("env_id", "system", "kind"),
    [
        ("Dubins3D-v0", Dubins3D, "reach"),
        ("NarrowPassage-v0", NarrowPassage, "reach-avoid"),
        ("Quadrotor-v0", Quadrotor, "avoid"),
        ("MultiVehicle12D-v0", MultiVehicle12D, "avoid"),
        ("MultiVehicle15D-v0", MultiVehicle15D, "avoid"),
    ],
)
def test_ids_build_their_systems(env_id, system, kind):
    env = gym.make(env_id).unwrapped
    assert type(env.system) is system and env.scene.kind == kind and env.scene.disturbance is None
    assert env.action_space.shape == (env.system.control_dim,)


def test_quadrotor_steps_at_a_hundredth_from_unit_quaternions():
    env = gym.make("Quadrotor-v0").unwrapped
    assert env.scene.dt == 0.01 and env.scene.max_steps == 100
    for seed in range(5):
        obs, info = env.reset(seed=seed)
        assert np.linalg.norm(env.state[3:7]) == pytest.approx(1.0) and info["margin"] > 0
    with pytest.raises(ValueError, match="unit_norm"):
        UniformSafe(unit_norm=(3,))
    with pytest.raises(ValueError, match="unit_norm"):
        UniformSafe(unit_norm=(3, 40)).sample(Quadrotor(), np.random.default_rng(0))


# ---------------------------------------------------------------------- PettingZoo
@pytest.mark.filterwarnings("ignore:unknown reset option")  # parallel_api_test resets with options={"options": 1}
@pytest.mark.parametrize(
    "make",
    [
        lambda: parallel_env("four-car-12d"),
        lambda: parallel_env("five-car-15d"),
        lambda: parallel_env(system="narrowpassage"),
        lambda: parallel_env(system=NarrowPassage(avoid_only=True)),
    ],
    ids=["four-car-12d", "five-car-15d", "narrowpassage", "narrowpassage-avoid"],
)
def test_parallel_api(make):
    parallel_api_test(make(), num_cycles=30)


def test_agents_are_groups_of_inputs():
    env = parallel_env(system="narrowpassage")
    assert env.possible_agents == ["car_1", "car_2"] and not env.per_car
    assert env.control_indices("car_1") == (0, 1) and env.control_indices("car_2") == (2, 3)
    assert env.action_space("car_2").shape == (2,)
    with pytest.raises(ValueError, match="control_indices"):
        env.control_index("car_1")
    four = parallel_env("four-car-12d")
    assert four.per_car and four.possible_agents == [f"car_{i}" for i in range(1, 5)]
    assert [four.control_index(a) for a in four.possible_agents] == [0, 1, 2, 3]


def _team_episode(state):
    env = parallel_env(system="narrowpassage")
    _, infos = env.reset(options={"state": state})
    assert all(info["outcome"] is None for info in infos.values())
    for _ in range(env.scene.max_steps):
        _, rewards, terms, truncs, infos = env.step({a: np.zeros(2, dtype=np.float32) for a in env.agents})
        if not env.agents:
            return rewards, terms, truncs, infos
        assert all(info["outcome"] is None for info in infos.values()) and set(rewards.values()) == {0.0}
    raise AssertionError("the team episode never ended")


@pytest.mark.parametrize(
    ("state", "outcome", "reward"),
    [
        # each car 2.5 short of its goal (reached within L = 2) and driving at it
        ((3.5, -1.4, 0.0, 3.0, 0.0, -3.5, 1.4, math.pi, 3.0, 0.0), "reached", 1.0),
        # the two cars head-on, 3 apart (a collision within L = 2)
        ((2.5, 1.0, math.pi, 5.0, 0.0, -0.5, 1.0, 0.0, 5.0, 0.0), "collided", -1.0),
    ],
)
def test_narrow_passage_team_ends_together_with_one_outcome(state, outcome, reward):
    rewards, terms, truncs, infos = _team_episode(state)
    assert terms == {"car_1": True, "car_2": True} and truncs == {"car_1": False, "car_2": False}
    assert rewards == {"car_1": reward, "car_2": reward}
    assert infos["car_1"]["outcome"] == infos["car_2"]["outcome"] == outcome
    assert infos["car_1"]["reached"] == (outcome == "reached") and infos["car_1"]["collision"] == (outcome != "reached")
    assert infos["car_1"]["control"].shape == (2,)


def test_system_declared_agents_and_systems_without_agents():
    class Piloted(Dubins3D):
        agent_inputs = {"pilot": (0,)}

    env = parallel_env(system=Piloted())
    assert env.possible_agents == ["pilot"] and agent_inputs(Piloted()) == {"pilot": (0,)}
    _, infos = env.reset(seed=0)
    assert infos["pilot"]["outcome"] is None

    class Lopsided(Dubins3D):
        agent_inputs = {"a": (0,), "b": (0,)}

    with pytest.raises(ValueError, match="exactly one agent"):
        parallel_env(system=Lopsided())
    with pytest.raises(ValueError, match="quadrotor is an avoid problem without agents"):
        MultiVehicleParallelEnv(system="quadrotor")


# ---------------------------------------------------------------------- reach envs
def test_reach_envs_names_every_id_and_scene(capsys):
    assert main(["envs"]) == 0
    out = capsys.readouterr().out
    ids = [*reach_envs.ENV_SCENES, *reach_envs.SYSTEM_ENVS, reach_envs.SYSTEM_ENV_ID]
    assert [i for i in ids if i not in out] == [] and [s for s in SCENES if s not in out] == []
    line = next(row for row in out.splitlines() if "NarrowPassage-v0" in row)
    assert "kind=reach-avoid" in line and "state=10D" in line and "action=4" in line and "agents=2" in line
    assert "car_1 acts inputs [0, 1], car_2 acts inputs [2, 3]" in out


def test_safety_filter_wraps_the_team_env_with_each_driver_acting_two_inputs():
    """The PettingZoo filter wrapper assembles the joint input from each agent's inputs (NarrowPassage's
    drivers act (a, psi) each), filters it as one input, and hands each driver back its two inputs."""
    import torch

    from safety.filters.wrappers import SafetyFilterParallelWrapper
    from training.network import NeuralValueFunction, ValueNetwork

    torch.manual_seed(0)
    vf = NeuralValueFunction(ValueNetwork(NarrowPassage(), "ssssl", width=16))
    penv = SafetyFilterParallelWrapper(parallel_env(system="narrowpassage"), vf, threshold=0.0)
    penv.reset(seed=0)
    _, _, _, _, infos = penv.step({a: np.array([0.5, -0.25], dtype=np.float32) for a in penv.agents})
    assert set(infos) == {"car_1", "car_2"}
    for info in infos.values():
        assert info["nominal_action"].shape == (2,) and info["applied_action"].shape == (2,)
        if not info["filter_intervened"]:
            np.testing.assert_allclose(info["applied_action"], [0.5, -0.25], rtol=1e-6)
    with pytest.raises(ValueError, match=r"action of 'car_1' must have shape \(2,\)"):
        penv.step({a: np.zeros(1, dtype=np.float32) for a in penv.agents})


def test_a_disc_of_thrust_takes_actions_inside_the_disc_and_scales_the_rest_onto_it():
    """The rocket's action space is the unit square over the disc's bounding box: an action inside the
    unit disc is the thrust c + r a, one outside is scaled back onto the disc (never an input the
    system cannot take); the vector env maps the same way; the filter projects a nominal thrust the
    same way; what needs box inputs refuses the disc by name."""
    import torch

    from reach.systems import RocketLanding
    from reach.systems.box import project_inputs
    from reach_envs.spaces import inputs_of_actions
    from safety.value_policies import GreedyPolicy
    from training.network import NeuralValueFunction, ValueNetwork

    disc = RocketLanding().control_bounds
    np.testing.assert_allclose(inputs_of_actions(np.array([0.3, -0.4]), disc), [75.0, -100.0])
    np.testing.assert_allclose(inputs_of_actions(np.array([1.0, 1.0]), disc), [250 / math.sqrt(2)] * 2)
    np.testing.assert_allclose(inputs_of_actions(np.array([[3.0, 0.0]]), disc), [[250.0, 0.0]])  # clipped first
    u = torch.tensor([[300.0, 400.0], [10.0, 20.0]], dtype=torch.float64)
    torch.testing.assert_close(
        project_inputs(u, disc), torch.tensor([[150.0, 200.0], [10.0, 20.0]], dtype=torch.float64)
    )
    env = gym.make("RocketLanding-v0").unwrapped
    env.reset(seed=0, options={"state": [0.0, 100.0, 0.0, 0.0, 0.0, 0.0]})
    env.step(np.array([1.0, 1.0], dtype=np.float32))  # the thrust at 45 degrees on the disc's edge
    from reach.integrators import make_stepper
    from reach.systems import FLOAT

    step = make_stepper(env.system, 0.01, env.scene.integrator, FLOAT)
    expected = step([0.0, 100.0, 0.0, 0.0, 0.0, 0.0], [250 / math.sqrt(2)] * 2, [])
    np.testing.assert_allclose(env.state, expected, rtol=1e-6)
    venv = reach_envs.make_vector_env("rocketlanding", 2, dt=0.01)
    venv.reset(seed=0, options={"state": np.array([[0.0, 100.0, 0.0, 0.0, 0.0, 0.0]] * 2)})
    venv.step(np.array([[1.0, 1.0], [0.0, 0.0]], dtype=np.float32))
    assert venv.state[0, 4] == pytest.approx(env.state[4], rel=1e-9)
    vf = NeuralValueFunction(ValueNetwork(RocketLanding(), "ssl", width=8))
    with pytest.raises(ValueError, match=r"the greedy policy needs box inputs.*ball of radius 250"):
        GreedyPolicy(vf, step=0.01, dt=0.01)

    class TwoPilots(RocketLanding):  # one pilot per thrust component: agents whose inputs a disc couples
        agent_inputs = {"pilot_1": (0,), "pilot_2": (1,)}

    with pytest.raises(ValueError, match="the PettingZoo env needs box inputs"):
        MultiVehicleParallelEnv(system=TwoPilots())
