"""Reach, avoid and reach-avoid: the kind is declared once in the system; the game's directions, the
boundary value and the grid solver's variational inequality follow from it, and tools that do not
yet handle a kind refuse it by name."""

from __future__ import annotations

import math

import pytest
import torch

from groundtruth import SolverSettings, solve
from reach.systems import TORCH, Dubins3D, DubinsReachAvoid, make_system
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Box
from reach.systems.problem import KINDS, PROBLEMS

GRID = 41
#: a coarser grid for the 2 s reach-avoid solves (they take twice the steps of a 1 s one)
SMALL = 31


def _values(solution, x: torch.Tensor, t: float) -> torch.Tensor:
    return solution.value(x, t)


@pytest.fixture(scope="module")
def reach_solution():
    return solve(Dubins3D("reach"), GRID, [0.0, 0.5, 1.0], settings=SolverSettings(compile=False), progress=False)


def test_the_kind_sets_the_game_and_the_meaning_of_the_sublevel_set():
    assert KINDS == ("avoid", "reach", "reach-avoid")
    reach, avoid, both = Dubins3D("reach"), Dubins3D("avoid"), DubinsReachAvoid()
    assert (avoid.control_objective, avoid.disturbance_objective) == ("max", "min")
    assert (reach.control_objective, reach.disturbance_objective) == ("min", "max")
    assert (both.control_objective, both.disturbance_objective) == ("min", "max")
    assert not avoid.problem.reaches and reach.problem.reaches and both.problem.has_constraint
    assert "reached" in PROBLEMS["reach"].sublevel_meaning
    # the optimal turn of a reach problem is the opposite of the avoid problem's, from one derivation
    x = reach.sample_states(64, torch.Generator().manual_seed(0))
    p = torch.randn(64, 3, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(reach.optimal_control(x, p), -avoid.optimal_control(x, p))
    # and the Hamiltonian is DeepReach's hand-written one for each mode (restated here)
    drift = 0.6 * (torch.cos(x[:, 2]) * p[:, 0] + torch.sin(x[:, 2]) * p[:, 1])
    torch.testing.assert_close(reach.hamiltonian(x, p), drift - 1.1 * p[:, 2].abs())
    torch.testing.assert_close(avoid.hamiltonian(x, p), drift + 1.1 * p[:, 2].abs())


def test_a_reach_tube_matches_the_straight_line_time_to_the_target(reach_solution):
    """Facing the target, the car drives straight at it: V is the least margin along that path,
    ``max(d - v T, 0) - goalR``, so it reaches within T from distances up to goalR + v T (0.85)."""
    d = torch.linspace(0.3, 0.98, 35, dtype=torch.float64)
    x = torch.stack([d, torch.zeros_like(d), torch.full_like(d, math.pi)], dim=-1)  # at (d, 0) facing -x
    v = _values(reach_solution, x, 1.0)
    exact = torch.clamp(d - 0.6 * 1.0, min=0.0) - 0.25  # the closest it gets to the centre, less goalR
    assert float((v - exact).abs().max()) < 0.03
    inside = d < 0.85 - 0.05
    outside = d > 0.85 + 0.05
    assert bool((v[inside] < 0).all()) and bool((v[outside] > 0).all())


def test_the_set_is_inside_the_tube_and_the_target_is_reached_at_once(reach_solution):
    system = Dubins3D("reach")
    brs = solve(system, GRID, [0.0, 0.5, 1.0], settings=SolverSettings(compile=False, tube="set"), progress=False)
    x = system.sample_states(4000, torch.Generator().manual_seed(2), dtype=torch.float64)
    tube, exact_time = _values(reach_solution, x, 1.0), _values(brs, x, 1.0)
    # reach *at* T is harder than reach *by* T (up to the 41-node grid's diffusion, 1.1e-3 here)
    assert bool((exact_time >= tube - 2e-3).all())
    target = system.target_margin(x) < -0.05
    assert bool((_values(reach_solution, x[target], 0.5) < 0).all())  # already there


def test_reach_avoid_without_an_obstacle_is_reach(reach_solution):
    """A negligible wind and an obstacle far outside the domain: the reach-avoid value is the reach value."""
    free = DubinsReachAvoid(
        wind=1e-9, goal=(0.0, 0.0), goal_radius=0.25, obstacle=(30.0, 30.0), obstacle_radius=0.01, horizon=1.0
    )
    solution = solve(free, GRID, [0.0, 0.5, 1.0], settings=SolverSettings(compile=False), progress=False)
    x = free.sample_states(4000, torch.Generator().manual_seed(3), dtype=torch.float64)
    diff = (_values(solution, x, 1.0) - _values(reach_solution, x, 1.0)).abs()
    assert float(diff.max()) < 1e-4


def test_an_obstacle_blocks_the_straight_path_and_is_never_entered():
    system = DubinsReachAvoid()
    solution = solve(system, SMALL, [0.0, 2.0], settings=SolverSettings(compile=False), progress=False)
    nodes = solution.grid.columns(torch.float64, "cpu")
    v = solution.values[-1].double()
    g = torch.broadcast_to(system.constraint_margin_columns(nodes, TORCH), v.shape)
    assert bool((v >= -g - 1e-6).all())  # V >= -g at every node: from inside the obstacle, never
    assert bool((v[g < 0] > 0).all())
    # behind the obstacle, facing the goal: the straight line crosses the obstacle, so it must go round
    behind = torch.tensor([[-0.3, 0.0, 0.0]], dtype=torch.float64)
    free = DubinsReachAvoid(obstacle=(30.0, 30.0), obstacle_radius=0.01)
    free_solution = solve(free, SMALL, [0.0, 2.0], settings=SolverSettings(compile=False), progress=False)
    assert float(_values(solution, behind, 2.0)) > float(_values(free_solution, behind, 2.0)) + 0.05
    assert float(_values(free_solution, behind, 2.0)) < 0  # without the obstacle: straight there in 2 s
    assert solution.metadata["scheme"]["kind"] == "reach-avoid"


class _NoConstraint(ControlAffineSystem):
    """A reach-avoid system that forgot its constraint margin."""

    name = "noconstraint"
    kind = "reach-avoid"
    state_names = ("x",)
    periodic = (False,)
    domain = ((-1.0, 1.0),)
    control_bounds = Box.symmetric([1.0])
    horizon = 1.0

    def drift(self, x, xp):
        return [0.0 * x[0]]

    def control_matrix(self, x, xp):
        return {(0, 0): 1.0}

    def target_margin_columns(self, x, xp):
        return xp.abs(x[0]) - 0.1


def test_bad_declarations_fail_at_construction_naming_the_field():
    with pytest.raises(ValueError, match="a reach-avoid system must define constraint_margin_columns"):
        _NoConstraint()

    class Unknown(_NoConstraint):
        kind = "escape"

    with pytest.raises(ValueError, match=r"kind must be one of \('avoid', 'reach', 'reach-avoid'\), got 'escape'"):
        Unknown()

    class OldStyle(_NoConstraint):
        kind = "reach"
        control_objective = "min"

    with pytest.raises(ValueError, match=r"declare kind = .* instead of control_objective"):
        OldStyle()

    class Scalar(_NoConstraint):
        kind = "reach"

        def target_margin_columns(self, x, xp):
            return 0.5

    with pytest.raises(ValueError, match=r"target_margin_columns must return one value per state"):
        Scalar()
    with pytest.raises(ValueError, match="set_mode must be one of"):
        Dubins3D("escape")


def test_a_filter_that_does_not_suit_a_kind_refuses_it_by_name():
    from safety import SafetyFilter
    from training import NeuralValueFunction, ValueNetwork

    system = make_system("dubinsreachavoid")
    vf = NeuralValueFunction(ValueNetwork(system, "ssl", width=8))
    x = system.sample_states(4)
    with pytest.raises(ValueError, match="smooth filter serves avoid problems only; dubinsreachavoid is a reach-avoid"):
        SafetyFilter(vf, kind="smooth")
    assert system.terminal_margin_columns(TORCH.unbind(x), TORCH).shape == (4,)
