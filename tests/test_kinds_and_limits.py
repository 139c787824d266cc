"""A system declares its kind and margins consistently, and its physics holds its own limits (issue 62,
points 5 and 6).

Point 5: a margin the kind has no use for (an obstacle on a reach problem, a target on an avoid one) or
a missing one is refused at construction, naming both; a margin returns real floating values, finite
at the domain states (NaN is refused naming the margin and the parameters, on construction and in
the grid solver); every built-in system refuses a constructor parameter of the wrong type or length
by name. Point 6: NarrowPassage's state-dependent input bounds stop its speed and steering at their
limits in discrete steps too (the env, the vector env, the torch stepper and rollouts), and its
``physical_controls`` refuses normalised inputs outside [-1, 1].
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

import reach_envs
from groundtruth import SolverSettings, solve
from reach.integrators import make_stepper
from reach.systems import (
    FLOAT,
    NUMPY,
    TORCH,
    Air3D,
    Car,
    Dubins3D,
    DubinsReachAvoid,
    MultiVehicle,
    MultiVehicle6D,
    MultiVehicle9D,
    NarrowPassage,
    ParameterizedVertDrone2D,
    Quadrotor,
    ReachAvoidRocketLanding,
    RelativePair,
    RocketLanding,
)
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Box
from reach.systems.problem import MARGIN_METHODS, PROBLEMS
from safety.verification.rollout import rollout


# ---------------------------------------------------------------- point 5: the kind's margins, and no other
class _Line(ControlAffineSystem):
    """``x' = u`` on [-1, 1]; each test's subclass declares a kind and some margins."""

    state_names = ("x",)
    periodic = (False,)
    domain = ((-1.0, 1.0),)
    control_bounds = Box.symmetric([1.0])
    horizon = 1.0

    def drift(self, x, xp):
        return [0.0 * x[0]]

    def control_matrix(self, x, xp):
        return {(0, 0): 1.0}


def _line(kind: str, **margins) -> ControlAffineSystem:
    """An instance of a ``_Line`` of ``kind`` writing ``margins`` (method name -> function of x[0])."""
    body = {"kind": kind}
    for method, fn in margins.items():
        body[method] = lambda self, x, xp, fn=fn: fn(x[0])
    return type(f"Line_{kind.replace('-', '_')}", (_Line,), body)()


def _l(v):
    return v - 0.5


def _g(v):
    return v + 0.5


def test_the_table_of_margins_each_kind_writes_and_must_not_write():
    assert PROBLEMS["avoid"].margin_methods == ("failure_margin_columns",)
    assert PROBLEMS["reach"].margin_methods == ("target_margin_columns",)
    assert PROBLEMS["reach-avoid"].margin_methods == ("target_margin_columns", "constraint_margin_columns")
    for problem in PROBLEMS.values():
        assert set(problem.margin_methods) | set(problem.foreign_margins) == set(MARGIN_METHODS)
        assert not set(problem.margin_methods) & set(problem.foreign_margins)
    # each kind with exactly its margins is accepted
    _line("avoid", failure_margin_columns=_l)
    _line("reach", target_margin_columns=_l)
    both = _line("reach-avoid", target_margin_columns=_l, constraint_margin_columns=_g)
    x = torch.linspace(-1, 1, 5, dtype=torch.float64)[:, None]
    torch.testing.assert_close(both.failure_margin(x), both.constraint_margin(x))  # the default
    _line("reach-avoid", target_margin_columns=_l, constraint_margin_columns=_g, failure_margin_columns=_g)


@pytest.mark.parametrize(
    ("kind", "margins", "message"),
    [
        # a margin the kind has no use for: silently dropped before, refused now naming both
        ("reach", {"target_margin_columns": _l, "constraint_margin_columns": _g},
         r"kind = 'reach' but constraint_margin_columns is written: a reach problem has no constraint"),
        ("avoid", {"failure_margin_columns": _l, "constraint_margin_columns": _g},
         r"kind = 'avoid' but constraint_margin_columns is written: an avoid problem has no constraint"),
        ("avoid", {"failure_margin_columns": _l, "target_margin_columns": _l},
         r"kind = 'avoid' but target_margin_columns is written: an avoid problem has no target"),
        ("reach", {"target_margin_columns": _l, "failure_margin_columns": _l},
         r"kind = 'reach' but failure_margin_columns is written: a reach problem has no failure set"),
        ("reach-avoid", {"target_margin_columns": _l, "constraint_margin_columns": _g, "failure_margin_columns": _l},
         r"kind = 'reach-avoid' but failure_margin_columns is written: .* where its constraint fails"),
        # a margin the kind needs, missing
        ("avoid", {"target_margin_columns": _l}, r"an avoid system must define failure_margin_columns"),
        ("reach", {"failure_margin_columns": _l}, r"a reach system must define target_margin_columns"),
        ("reach", {}, r"a reach system must define target_margin_columns"),
        ("reach-avoid", {"target_margin_columns": _l}, r"a reach-avoid system must define constraint_margin_columns"),
        ("reach-avoid", {"constraint_margin_columns": _g}, r"a reach-avoid system must define target_margin_columns"),
    ],
)  # fmt: skip
def test_margins_that_contradict_the_kind_are_refused_naming_both(kind, margins, message):
    with pytest.raises(ValueError, match=message):
        _line(kind, **margins)


def test_a_subclass_that_changes_the_kind_inherits_no_margin_it_would_ignore():
    class Corridor(_Line):
        kind = "reach-avoid"

        def target_margin_columns(self, x, xp):
            return x[0] - 0.5

        def constraint_margin_columns(self, x, xp):
            return x[0] + 0.5

    class ReachOnly(Corridor):  # the obstacle would be dropped
        kind = "reach"

    Corridor()
    with pytest.raises(ValueError, match="kind = 'reach' but constraint_margin_columns is written"):
        ReachOnly()


def test_built_in_systems_that_switch_kind_write_only_that_kinds_margins():
    x = TORCH.unbind(torch.zeros(2, 10, dtype=torch.float64))
    for system, absent in (
        (Dubins3D("avoid"), "target_margin_columns"),
        (Dubins3D("reach"), "failure_margin_columns"),
        (Quadrotor(set_mode="avoid"), "target_margin_columns"),
        (Quadrotor(set_mode="reach"), "failure_margin_columns"),
        (NarrowPassage(avoid_only=True), "target_margin_columns"),
        (NarrowPassage(avoid_only=True), "constraint_margin_columns"),
        (RocketLanding(), "constraint_margin_columns"),
    ):
        with pytest.raises(NotImplementedError, match=absent):
            getattr(system, absent)(x[: system.state_dim], TORCH)


@pytest.mark.parametrize(
    ("margin", "dtype"),
    [
        (lambda v: v > 0.5, "torch.bool"),
        (lambda v: (v > 0.5).long(), "torch.int64"),
        (lambda v: (v > 0).int(), "int32"),
    ],
)
def test_a_margin_of_booleans_or_integers_is_refused_naming_it(margin, dtype):
    with pytest.raises(ValueError, match=rf"target_margin_columns must return real floating values.*{dtype}"):
        _line("reach", target_margin_columns=margin)
    with pytest.raises(ValueError, match=rf"constraint_margin_columns must return real floating values.*{dtype}"):
        _line("reach-avoid", target_margin_columns=_l, constraint_margin_columns=margin)


class _Disc(_Line):
    """Reach ``|x - centre| <= radius``; its radius enters as ``sqrt(radius_squared)``."""

    kind = "reach"

    def __init__(self, centre: float = 0.0, radius_squared: float = 0.04) -> None:
        self.centre, self.radius_squared = centre, radius_squared

    def parameters(self):
        return {"centre": self.centre, "radius_squared": self.radius_squared}

    def target_margin_columns(self, x, xp):
        return xp.abs(x[0] - self.centre) - xp.sqrt(0.0 * x[0] + self.radius_squared)


def test_a_margin_that_is_nan_for_some_parameters_is_refused_naming_them():
    _Disc()
    with pytest.raises(ValueError, match=r"target_margin_columns returned NaN at the state \[.*\], with parameters "
                       r"\{centre=0.0, radius_squared=-0.04\}"):  # fmt: skip
        _Disc(radius_squared=-0.04)
    with pytest.raises(ValueError, match=r"returned NaN .*\(not finite: centre\)"):
        _Disc(centre=math.nan)
    with pytest.raises(ValueError, match=r"returned inf .*\(not finite: centre\)"):
        _Disc(centre=-math.inf)


class _Hole(_Line):
    """A reach system whose margin is NaN at x = 0 only: a grid node, never a probed state."""

    kind = "reach"

    def target_margin_columns(self, x, xp):
        return xp.where(x[0] == 0.0, math.nan, xp.abs(x[0]) - 0.5)


def test_the_grid_solver_names_the_margin_that_breaks_it():
    system = _Hole()  # its probe states miss x = 0
    with pytest.raises(ValueError, match=r"_Hole: target_margin_columns returned NaN at the state \[0\.0\]"):
        solve(system, 21, [0.0, 0.1], settings=SolverSettings(compile=False), progress=False)


# ---------------------------------------------------------------- point 5: constructor parameters by name
@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Dubins3D(set_mode=["reach"]), r"Dubins3D: set_mode must be one of"),
        (lambda: Dubins3D(goalR="0.25"), r"Dubins3D: goalR must be a real number"),
        (lambda: Dubins3D(horizon=True), r"Dubins3D: horizon must be a real number"),
        (lambda: DubinsReachAvoid(wind=[0.1, 0.1]), r"DubinsReachAvoid: wind must be a real number"),
        (lambda: DubinsReachAvoid(goal=(0.7,)), r"DubinsReachAvoid: goal must have 2 coordinates, got 1"),
        (lambda: Air3D(horizon="1"), r"Air3D: horizon must be a real number"),
        (lambda: Air3D(horizon=True), r"Air3D: horizon must be a real number"),
        (lambda: Air3D(half_width=math.nan), r"Air3D: half_width must be positive and finite"),
        (lambda: RelativePair(role_2=["control"]), r"RelativePair: role_2 must be one of"),
        (lambda: RelativePair(speed_1=None), r"RelativePair: speed_1 must be a real number"),
        (lambda: MultiVehicle(5), r"MultiVehicle: cars must be a list of Car"),
        (lambda: MultiVehicle("ab"), r"MultiVehicle: cars must be a list of Car"),
        (lambda: MultiVehicle([{"speed": 1.0}, {"speed": 1.0, "max_turn_rate": 1.0}]), r"cars\[0\] must have speed"),
        (lambda: MultiVehicle([Car(1.0, 1.0), 3]), r"MultiVehicle: cars\[1\] must be a Car"),
        (lambda: MultiVehicle([Car(1.0, 1.0)] * 2, horizon="1"), r"MultiVehicle: horizon must be a real number"),
        (lambda: MultiVehicle([Car(1.0, 1.0)] * 2, horizon=True), r"MultiVehicle: horizon must be a real number"),
        (lambda: Car(1.0, 1.0, name=3), r"Car: name must be a string, got 3"),
        (lambda: Car(1.0, 1.0, role=["control"]), r"role must be one of"),
        (lambda: MultiVehicle9D(speed="0.6"), r"speed must be a real number"),
        (lambda: MultiVehicle6D(max_turn_rate=[3.0]), r"max_turn_rate must be a real number"),
        (lambda: NarrowPassage(avoid_fn_weight=[1.0]), r"NarrowPassage: avoid_fn_weight must be a real number"),
        (lambda: NarrowPassage(horizon=math.nan), r"NarrowPassage: horizon must be positive and finite"),
        (lambda: Quadrotor(set_mode=["avoid"]), r"Quadrotor: set_mode must be one of"),
        (lambda: Quadrotor(thrust_max="20"), r"Quadrotor: thrust_max must be a real number"),
        (lambda: ParameterizedVertDrone2D(gravity=True), r"ParameterizedVertDrone2D: gravity must be a real number"),
        (lambda: RocketLanding(horizon=(1.0,)), r"RocketLanding: horizon must be a real number"),
        (lambda: ReachAvoidRocketLanding(horizon=-1.0), r"ReachAvoidRocketLanding: horizon must be positive"),
    ],
)
def test_every_built_in_system_refuses_a_bad_parameter_by_name(build, message):
    with pytest.raises(ValueError, match=message):
        build()


# ---------------------------------------------------------------- point 6: NarrowPassage keeps its limits
LOW, HIGH = NarrowPassage.speed_limits
STEER = NarrowPassage.steer_limit
#: car 1 at full throttle from 6.49, car 2 at full brake from 0.01; steering 0.005 short of each stop
EDGE = [-6.0, -1.4, 0.0, 6.49, STEER - 0.005, 6.0, 1.4, math.pi - 0.1, 0.01, -STEER + 0.005]
PUSH = [1.0, 1.0, -1.0, -1.0]  # throttle and steer up on car 1, brake and steer down on car 2


def _within_limits(states) -> bool:
    x = np.asarray(states, dtype=np.float64).reshape(-1, 10)
    speeds, steering = x[:, [3, 8]], x[:, [4, 9]]
    return bool(((speeds >= LOW) & (speeds <= HIGH)).all() and (np.abs(steering) <= STEER).all())


def test_without_the_limits_a_step_overshoots_them():
    """What the discrete step did before: the held input carried the state past both limits."""
    system = NarrowPassage()
    raw = [a + 0.02 * b for a, b in zip(EDGE, system.xdot_columns(EDGE, PUSH, [], FLOAT))]
    assert raw[3] > HIGH and raw[8] < LOW and raw[4] > STEER and raw[9] < -STEER


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_the_stepper_stops_at_the_limits_on_every_backend(integrator):
    system = NarrowPassage()
    for xp, x, u in (
        (FLOAT, EDGE, PUSH),
        (NUMPY, NUMPY.unbind(np.array([EDGE] * 3)), NUMPY.unbind(np.array([PUSH] * 3))),
        (TORCH, TORCH.unbind(torch.tensor([EDGE] * 3, dtype=torch.float64)), TORCH.unbind(torch.tensor([PUSH] * 3))),
    ):
        step = make_stepper(system, 0.02, integrator, xp)
        for _ in range(5):
            x = step(x, u, [])
        states = np.stack([np.asarray(c, dtype=np.float64) for c in x], axis=-1)
        assert _within_limits(states), (xp.name, states)
        assert np.allclose(states.reshape(-1, 10)[:, [3, 4, 8, 9]], [HIGH, STEER, LOW, -STEER])


def test_a_state_outside_its_limits_moves_as_the_dynamics_move_it():
    """Only a side the state started inside is kept: from above 6.5 full brake slows it as before."""
    system = NarrowPassage()
    x = list(EDGE)
    x[3], x[8] = 6.9, -0.5  # above the top, below the bottom: the other input's bound is 0 there
    step = make_stepper(system, 0.02, "euler", FLOAT)
    nxt = step(x, [-1.0, 0.0, 1.0, 0.0], [])
    assert nxt[3] == pytest.approx(6.9 - 4.0 * 0.02) and nxt[8] == pytest.approx(-0.5 + 2.0 * 0.02)
    assert step(x, [1.0, 0.0, -1.0, 0.0], [])[3] == 6.9  # the bound toward leaving further is 0


def test_the_env_keeps_the_limits_under_full_throttle_brake_and_steering():
    env = gym.make("NarrowPassage-v0")
    env.reset(seed=0, options={"state": EDGE})
    for _ in range(10):
        env.step(np.array(PUSH, dtype=np.float32))
        state = env.unwrapped.state
        assert _within_limits(state), state
    assert list(np.asarray(env.unwrapped.state)[[3, 4, 8, 9]]) == [HIGH, STEER, LOW, -STEER]
    noisy = gym.make("NarrowPassage-v0", process_noise=0.3)  # the noise keeps them too
    noisy.reset(seed=1, options={"state": EDGE})
    for _ in range(20):
        noisy.step(np.array(PUSH, dtype=np.float32))
        assert _within_limits(noisy.unwrapped.state)
    venv = reach_envs.make_vector_env("narrowpassage", 3)
    venv.reset(seed=0, options={"state": np.array([EDGE] * 3)})
    for _ in range(10):
        venv.step(np.array([PUSH] * 3, dtype=np.float32))
        assert _within_limits(venv.state)


class _Push:
    """A value function whose gradient asks for full throttle and steering up on car 1, full brake and
    steering down on car 2 (reach-avoid: the control minimises V)."""

    def __init__(self, system):
        self.system = system
        self.weights = torch.tensor([0, 0, 0, -1, -1, 0, 0, 0, 1, 1], dtype=torch.float64)

    def value(self, x, t):
        return (x * self.weights.to(x)).sum(-1)

    def gradient(self, x, t):
        return self.weights.to(x).expand_as(x)


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_rollouts_keep_the_limits(integrator):
    system = NarrowPassage()
    states = torch.tensor([EDGE] * 4, dtype=torch.float64)
    out = rollout(_Push(system), states, dt=0.02, horizon=0.2, integrator=integrator, record=True, progress=False,
                  dtype=torch.float64)  # fmt: skip
    assert _within_limits(out.trajectories.numpy())
    assert torch.equal(
        out.trajectories[-1, :, [3, 4, 8, 9]], torch.tensor([[HIGH, STEER, LOW, -STEER]] * 4, dtype=torch.float64)
    )


def test_physical_controls_refuses_normalised_inputs_outside_the_box():
    system = NarrowPassage()
    x = torch.tensor([EDGE], dtype=torch.float64)
    full = system.physical_controls(x, torch.tensor([PUSH], dtype=torch.float64))
    torch.testing.assert_close(full, torch.tensor([[2.0, 3 * math.pi, -4.0, -3 * math.pi]], dtype=torch.float64))
    for bad, name in ((1.5, "a1"), (-1.0001, "psi1"), (math.nan, "a2")):
        u = torch.zeros(1, 4, dtype=torch.float64)
        u[0, ("a1", "psi1", "a2").index(name)] = bad
        with pytest.raises(ValueError, match=rf"normalised control u must lie in \[-1, 1\], got {bad!r} for {name}"):
            system.physical_controls(x, u)


def test_limits_are_checked_on_construction_and_no_other_system_declares_any():
    class Periodic(_Line):
        kind = "reach"
        state_names = ("th",)
        periodic = (True,)
        domain = ((-math.pi, math.pi),)

        def target_margin_columns(self, x, xp):
            return xp.abs(x[0]) - 0.5

        def state_limits(self):
            return {0: (-1.0, 1.0)}

    with pytest.raises(ValueError, match="state_limits key 0 must index a non-periodic state dimension"):
        Periodic()

    class Upside(_Line):
        kind = "reach"

        def target_margin_columns(self, x, xp):
            return xp.abs(x[0]) - 0.5

        def state_limits(self):
            return {0: (1.0, -1.0)}

    with pytest.raises(ValueError, match=r"state_limits of x must be finite \(low, high\) with low < high"):
        Upside()
    for cls in (Air3D, Dubins3D, DubinsReachAvoid, Quadrotor, RocketLanding, MultiVehicle9D, ParameterizedVertDrone2D):
        assert cls().state_limits() == {}  # make_stepper returns the dynamics' step unchanged
