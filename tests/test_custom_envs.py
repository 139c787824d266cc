"""Environments of any system (issue 19, point 3): make_env, make_vector_env, ``Reach-v0``, the
projection view of systems that are not cars, and the scene guarantees for a user's system."""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import reach_envs
from reach.systems import FLOAT, NUMPY, Air3D
from reach_envs import make_env, make_vector_env
from reach_envs.policies import MarginPursuit, RandomDisturbance
from reach_envs.projection import FAILURE_RGB, ProjectionRenderer
from reach_envs.rendering import SceneRenderer
from reach_envs.scenes import Scene, system_scene
from reach_envs.views import make_renderer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import my_systems
from my_systems import DubinsAccel, DubinsAvoid

# As in test_envs.py: non-periodic dimensions are unbounded on purpose (states leave the domain).
JUSTIFIED = ("A Box observation space minimum value is -infinity", "A Box observation space maximum value is infinity")


def _check(env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    unexpected = [str(w.message) for w in caught if not any(j in str(w.message) for j in JUSTIFIED)]
    assert unexpected == []


def _run(env, steps=30):
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        if terminated or truncated:
            break


def _failure_pixels(frame):
    return int((np.abs(frame.astype(np.int64) - FAILURE_RGB).sum(axis=-1) <= 6).sum())


# ---------------------------------------------------------------------- construction and API checks
@pytest.mark.parametrize(
    "make",
    [
        lambda: make_env(DubinsAvoid()),
        lambda: make_env("my_systems:DubinsAccel", disturbance="random"),
        lambda: make_env("dubins-avoid", disturbance="pursue", process_noise=0.01),
        lambda: gym.make("Reach-v0", system=DubinsAvoid(), dt=0.02).unwrapped,  # spec: render check included
        lambda: gym.make("Reach-v0", system=DubinsAccel(), disturbance="pursue").unwrapped,
    ],
    ids=["instance", "import-path-2-controls", "registered-name", "gym-make", "gym-make-4d"],
)
def test_check_env_passes_for_user_systems(make):
    _check(make())


def test_make_env_builds_the_scene_from_the_system_and_fields():
    env = make_env("my_systems:DubinsAccel", dt=0.05, horizon=0.5, disturbance="random")
    assert isinstance(env.system, DubinsAccel) and env.scene.name == env.system.name
    assert (env.scene.dt, env.scene.max_steps, env.scene.disturbance) == (0.05, 10, "random")
    assert env.observation_space.shape == (4,) and env.action_space.shape == (2,)
    assert env.metadata["render_fps"] == 20
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([1.0, -3.0], dtype=np.float32))  # out of range: clipped
    assert info["control"].tolist() == [1.5, -1.0]  # the ends of each control's box
    env = gym.make("Reach-v0", system=DubinsAvoid(radius=0.3), name="mine", view_dims=("px", "heading"))
    assert env.unwrapped.scene.name == "mine" and env.unwrapped.scene.view_dims == (0, 2)
    assert env.unwrapped.system.radius == 0.3


def test_make_env_takes_a_car_system_and_draws_cars():
    env = make_env("air3d", render_mode="rgb_array")
    assert isinstance(env.system, Air3D) and env.scene.disturbance is None  # a system, not the named scene
    assert isinstance(make_renderer(env.scene), SceneRenderer)
    assert isinstance(make_renderer(make_env(DubinsAvoid()).scene), ProjectionRenderer)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: make_env("no-such-system"), "no-such-system"),
        (lambda: make_env("my_systems:NoSuchClass"), "NoSuchClass"),
        (lambda: make_env("no_such_module_xyz:Car"), "no_such_module_xyz"),
        (lambda: make_env("not a path:"), "import path"),
        (lambda: make_env(42), "42"),
        (lambda: make_env(Scene(DubinsAvoid())), "got a Scene"),
        (lambda: make_env(DubinsAvoid(), speedd=1.0), r"unknown field\(s\) \['speedd'\]"),
        (lambda: make_env(DubinsAvoid(), scene="air3d"), "not both"),
        (lambda: reach_envs.make_vector_env(DubinsAvoid(), 2, scene="air3d"), "not both"),
        (lambda: gym.make("Air3D-v0", system=DubinsAvoid()), "not both"),
        (lambda: gym.make("Reach-v0"), "no system or scene given"),
        (lambda: gym.make_vec("Reach-v0", num_envs=2), "no system or scene given"),
        (lambda: make_env(DubinsAvoid(), view_dims=(0, 0)), "view_dims must name two different"),
        (lambda: make_env(DubinsAvoid(), view_dims=(0, 3)), "view_dims entry 3"),
        (lambda: make_env(DubinsAvoid(), view_dims=(0, "speed")), "view_dims entry 'speed'"),
        (lambda: make_env(DubinsAvoid(), view_dims=(True, 1)), "view_dims entry True"),
        (lambda: make_env(DubinsAvoid(), view_dims=0), "view_dims must be a pair"),
        (lambda: make_env(DubinsAvoid(), view_dims=(0, 1, 2)), "view_dims must be a pair"),
        (lambda: make_env("air3d", view_dims=(0, 1)), "view_dims is for"),
        (lambda: make_env(DubinsAvoid(), arena=1.0), "arena"),
        (lambda: make_env(DubinsAvoid(), initial_state=[0.0, 0.0]), "initial_state"),
    ],
)
def test_bad_input_fails_naming_it(make, message):
    with pytest.raises(ValueError, match=message):
        make()


# ---------------------------------------------------------------------- vector env
def test_vector_env_steps_auto_resets_and_matches_single_envs(lockstep):
    n = 4
    venv = gym.make_vec("Reach-v0", num_envs=n, system=DubinsAvoid(), disturbance="pursue", horizon=0.4)
    assert type(venv).__name__ == "ReachVectorEnv" and venv.observation_space.shape == (n, 3)
    singles = [make_env(DubinsAvoid(), disturbance="pursue", horizon=0.4) for _ in range(n)]
    obs, _ = venv.reset(seed=3)
    np.testing.assert_array_equal(obs, np.stack([env.reset(seed=3 + i)[0] for i, env in enumerate(singles)]))

    def check_info(info):
        assert info["disturbance"].shape == (n, 2)

    resets = lockstep(venv, singles, 50, 1.2, check_info)
    assert resets >= n  # every sub-env reached the 20-step horizon at least once


def test_make_vector_env_with_two_controls_renders_one_projection_per_env():
    venv = make_vector_env("my_systems:DubinsAccel", 3, render_mode="rgb_array", disturbance="random")
    obs, info = venv.reset(seed=0)
    assert obs.shape == (3, 4) and info["margin"].shape == (3,)
    obs, rew, te, tr, info = venv.step(np.zeros((3, 2), dtype=np.float32))
    assert info["control"].shape == (3, 2) and info["disturbance"].shape == (3, 2)
    frames = venv.render()
    assert len(frames) == 3 and all(f.shape == (400, 400, 3) and f.dtype == np.uint8 for f in frames)
    assert not np.array_equal(frames[0], frames[1])
    venv.close()


# ---------------------------------------------------------------------- projection view
def test_projection_frames_draw_the_failure_set_of_the_system():
    env = make_env(DubinsAvoid(), render_mode="rgb_array")
    env.reset(options={"state": [-1.0, -1.0, 0.0]})
    frame = env.render()
    assert frame.shape == (400, 400, 3) and frame.dtype == np.uint8
    # the disc (radius 0.4 in a 3 x 3 view) covers pi * 0.16 / 9 of the axes: about 5.6 %
    axes = env._renderer.axes.get_window_extent()
    expected = math.pi * 0.4**2 / 9.0 * axes.width * axes.height
    assert 0.7 * expected < _failure_pixels(frame) < 1.3 * expected
    env.step(np.zeros(1, dtype=np.float32))
    later = env.render()
    assert not np.array_equal(frame, later)  # the marker moved and the clock advanced
    # a smaller disc in another instance: fewer failure pixels
    small = make_env(DubinsAvoid(radius=0.2), render_mode="rgb_array")
    small.reset(options={"state": [-1.0, -1.0, 0.0]})
    assert 0 < _failure_pixels(small.render()) < 0.5 * _failure_pixels(frame)


def test_projection_holds_the_other_dimensions_at_the_current_state():
    # view (px, heading): the failure set is the disc's chord at the current py
    env = make_env(DubinsAvoid(), render_mode="rgb_array", view_dims=(0, 2))
    env.reset(options={"state": [-1.0, 0.2, 0.0]})  # py through the disc centre: widest chord
    through = _failure_pixels(env.render())
    env.reset(options={"state": [-1.0, 0.5, 0.0]})  # a shorter chord
    off = _failure_pixels(env.render())
    env.reset(options={"state": [-1.0, 1.2, 0.0]})  # py beyond the disc: the set leaves the view
    assert through > off > 0 and _failure_pixels(env.render()) == 0
    renderer = env._renderer
    mask = renderer.failure_mask([0.0, 0.2, 0.0])
    assert mask.shape == (96, 96) and mask.all(axis=0).sum() > 0  # l is independent of the heading


def test_failure_mask_is_one_batched_numpy_call(monkeypatch):
    system = DubinsAccel()
    renderer = ProjectionRenderer(system, (0, 1))
    calls = []
    original = DubinsAccel.failure_margin_columns

    def spy(self, x, xp):
        calls.append((xp, np.shape(x[0])))
        return original(self, x, xp)

    monkeypatch.setattr(DubinsAccel, "failure_margin_columns", spy)
    mask = renderer.failure_mask([0.0, 0.0, 0.5, 0.7])
    assert calls == [(NUMPY, (96, 96))]
    gx, gy = np.meshgrid(np.linspace(-1.5, 1.5, 96), np.linspace(-1.5, 1.5, 96))
    np.testing.assert_array_equal(mask, np.hypot(gx, gy) <= 0.4)
    renderer.close()


def test_default_view_dims_skip_periodic_dimensions():
    class HeadingFirst(DubinsAvoid):  # (heading, px, py) would be drawn on (px, py)
        state_names = ("heading", "px", "py")
        periodic = (True, False, False)

        def __init__(self) -> None:
            super().__init__()
            self.domain = ((-math.pi, math.pi), (-1.5, 1.5), (-1.5, 1.5))

        def drift(self, x, xp):
            return [0.0 * x[0], self.speed * xp.cos(x[0]), self.speed * xp.sin(x[0])]

        def control_matrix(self, x, xp):
            return {(0, 0): 1.0}

        def disturbance_matrix(self, x, xp):
            return {(1, 0): 1.0, (2, 1): 1.0}

        def failure_margin_columns(self, x, xp):
            return super().failure_margin_columns([x[1], x[2], x[0]], xp)

    from reach_envs.views import projected_view

    assert projected_view(system_scene(HeadingFirst())) == (1, 2)
    assert projected_view(system_scene(DubinsAccel())) == (0, 1)
    assert projected_view(system_scene(Air3D())) is None


# ---------------------------------------------------------------------- scene guarantees, user system
def test_trails_of_a_user_system_only_when_asked_for_and_rendered(created_figures):
    created = created_figures
    env = make_env(DubinsAvoid(), trails=True)  # trails asked for, but nothing is rendered
    env.reset(seed=0)
    _run(env, 10)
    assert created == [] and env._renderer is None and env._trails == []
    env = make_env(DubinsAvoid(), render_mode="rgb_array")  # rendered, but no trails asked for
    env.reset(seed=0)
    _run(env, 10)
    assert env._trails == []
    env.render()
    assert len(created) == 1
    env = make_env(DubinsAvoid(), render_mode="rgb_array", trails=True, view_dims=(1, 2))
    env.reset(seed=0)
    states = [env.state]
    for _ in range(5):
        env.step(np.ones(1, dtype=np.float32))
        states.append(env.state)
    assert env._trails == [[(s[1], s[2]) for s in states]]  # the projected states, one trail
    with_trail = env.render()
    env._record_trails = False
    assert not np.array_equal(with_trail, env.render())  # the trail is drawn


def test_no_disturbance_policy_call_for_a_user_system_without_a_disturbance(monkeypatch):
    calls = []
    for cls in (MarginPursuit, RandomDisturbance):
        original = cls.columns

        def spy(self, *args, _original=original, **kwargs):
            calls.append(type(self).__name__)
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(cls, "columns", spy)
    env = make_env(DubinsAvoid(), disturbance=None)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(1, dtype=np.float32))
    _run(env, 20)
    assert calls == [] and env.sim.calls["disturbance_policy"] == 0 and info["disturbance"].tolist() == [0.0, 0.0]
    for kind, cls in (("pursue", "MarginPursuit"), ("random", "RandomDisturbance")):
        calls.clear()
        env = make_env(DubinsAvoid(), disturbance=kind)
        env.reset(seed=0)
        _run(env, 20)
        assert calls and set(calls) == {cls} and len(calls) == env.sim.calls["disturbance_policy"]


@pytest.mark.parametrize(
    ("fields", "draws"),
    [
        ({}, False),
        ({"disturbance": "pursue"}, False),
        ({"disturbance": "random"}, True),
        ({"process_noise": 0.05}, True),
        ({"process_noise": 0.0}, False),
    ],
)
def test_random_numbers_for_a_user_system_only_with_noise_or_a_random_disturbance(fields, draws):
    env = make_env("my_systems:DubinsAccel", **fields)
    env.reset(seed=0)
    before = env.np_random.bit_generator.state
    _run(env, 20)
    assert (env.np_random.bit_generator.state != before) is draws
    assert (env.sim.calls["process_noise"] > 0) is ("process_noise" in fields and fields["process_noise"] > 0)


# ---------------------------------------------------------------------- disturbances on several states
def test_pursue_pushes_a_user_system_toward_its_failure_set_on_every_backend():
    system = DubinsAvoid()
    policy = MarginPursuit(system)
    rng = np.random.default_rng(0)
    # up and right of the disc centre (0.3, 0.2): the wind blows down and left, at full strength
    assert policy.columns([1.0, 1.0, 0.3], FLOAT, rng) == [-0.1, -0.1]
    # level with the centre, to its left: push right only (l does not change with py there)
    assert policy.columns([-0.5, 0.2, 0.0], FLOAT, rng) == [0.1, 0.0]
    states = system.sample_states_numpy(rng, 64)
    batch = np.stack(policy.columns(NUMPY.unbind(states), NUMPY, rng), axis=-1)
    single = np.array([policy.columns(s.tolist(), FLOAT, rng) for s in states])
    np.testing.assert_array_equal(batch, single)
    toward = np.array([system.centre]) - states[:, :2]
    assert (np.sign(batch) == np.sign(toward)).all()


def test_pursue_and_random_disturbances_move_several_states():
    x0 = [-0.3, -0.5, 0.0, 0.5]
    finals = {}
    for kind in (None, "pursue", "random"):
        env = make_env("my_systems:DubinsAccel", disturbance=kind, initial_state=x0)
        env.reset(seed=0)
        ds = []
        for _ in range(10):
            _, _, terminated, truncated, info = env.step(np.zeros(2, dtype=np.float32))
            ds.append(info["disturbance"])
        ds = np.array(ds)
        assert ds.shape == (10, 2) and (np.abs(ds) <= 0.05 + 1e-12).all()
        finals[kind] = env.state
        if kind == "random":
            assert len(np.unique(ds[:, 0])) == 10 and len(np.unique(ds[:, 1])) == 10
        if kind == "pursue":  # the disc is centred at the origin: up and right of the car
            np.testing.assert_array_equal(ds, np.full((10, 2), 0.05))
    for kind in ("pursue", "random"):  # the wind moves both positions, nothing else
        moved = np.abs(finals[kind] - finals[None]) > 1e-9
        assert moved.tolist() == [True, True, False, False]
    assert np.linalg.norm(finals["pursue"][:2]) < np.linalg.norm(finals[None][:2])  # pushed toward the disc


def test_user_system_module_is_the_examples_one():
    assert my_systems.DubinsAvoid is DubinsAvoid  # the import path form resolves to the same class
    assert type(make_env("my_systems:DubinsAvoid").system) is DubinsAvoid


class _NaNMargin(DubinsAvoid):
    """A user system whose margin is NaN right of x = 0.5 (a sqrt of a negative, say)."""

    name = "nan-margin"

    def failure_margin_columns(self, x, xp):
        base = super().failure_margin_columns(x, xp)
        if xp is FLOAT:
            return math.nan if x[0] > 0.5 else base
        return np.where(x[0] > 0.5, np.nan, base) if xp is NUMPY else base  # torch: the checks at construction


class _NaNDrift(DubinsAvoid):
    """A user system whose drift is NaN right of x = 0.5."""

    name = "nan-drift"

    def drift(self, x, xp):
        out = super().drift(x, xp)
        if xp is FLOAT:
            return [math.nan if x[0] > 0.5 else out[0], *out[1:]]
        return [np.where(x[0] > 0.5, np.nan, out[0]), *out[1:]] if xp is NUMPY else out


@pytest.mark.parametrize(("system", "what"), [(_NaNMargin, "failure margin"), (_NaNDrift, "next state")])
def test_non_finite_user_physics_raise_naming_the_state(system, what):
    start = [0.6, 0.0, 0.0]
    with pytest.raises(ValueError, match=rf"{system.name}: the {what} is NaN or infinite at state \["):
        env = make_env(system(), disturbance=None)
        env.reset(seed=0, options={"state": start})
        for _ in range(3):
            env.step(np.zeros(1, dtype=np.float32))
    vec = make_vector_env(system(), num_envs=2, disturbance=None)
    with pytest.raises(ValueError, match=rf"{system.name}: the {what} is NaN or infinite at state \["):
        vec.reset(seed=0, options={"state": np.array([start, [-1.0, -1.0, 0.0]])})
        for _ in range(3):
            vec.step(np.zeros((2, 1), dtype=np.float32))
