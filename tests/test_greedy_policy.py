"""The greedy policy (a held step of V instead of grad V): what it picks, where it helps, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from reach.systems.base import ControlAffineSystem
from reach.systems.box import Box
from safety import SafetyFilter
from safety.value_loading import load_value_function
from safety.value_policies import GREEDY_STEP, GreedyPolicy, OptimalPolicy
from safety.verification.rollout import rollout
from safety.verification.verify import VerifySettings
from studies.filter_configs import FilterConfig
from studies.filter_episodes import evaluate_filters, outside_states


class _Plane(ControlAffineSystem):
    """x' = u on the plane, u in [-1, 1]^2; danger far from the origin (l > 0 inside radius 0.9)."""

    state_names = ("a", "b")
    periodic = (False, False)

    def __init__(self) -> None:
        self.domain = ((-1.0, 1.0), (-1.0, 1.0))
        self.control_bounds = Box.symmetric([1.0, 1.0])
        self.horizon = 1.0

    def drift(self, x, xp):
        return [0.0 * x[0], 0.0 * x[1]]

    def control_matrix(self, x, xp):
        return {(0, 0): 1.0, (1, 1): 1.0}

    def failure_margin_columns(self, x, xp):
        return 0.81 - x[0] ** 2 - x[1] ** 2


class _Analytic:
    """A value function given by a formula; its gradient by autograd (0 at the kink of abs)."""

    def __init__(self, system, formula):
        self.system = system
        self.formula = formula

    def value(self, x, t):
        return self.formula(x)

    def gradient(self, x, t):
        with torch.enable_grad():
            y = x.detach().clone().requires_grad_(True)
            (g,) = torch.autograd.grad(self.formula(y).sum(), y)
        return g


def _after_step(system, x, u, step=GREEDY_STEP):
    return x + step * u  # x' = u, held


def test_on_a_smooth_value_the_greedy_input_is_the_gradients():
    """Where V is smooth (and below l, as the exact value is) both pick the same box corner."""
    system = _Plane()
    vf = _Analytic(system, lambda x: x[..., 0] + 2 * x[..., 1] - 0.1)
    x = torch.tensor([[0.1, -0.2], [0.1, 0.1]])
    u_star = OptimalPolicy(vf).control(x, 1.0)
    assert torch.equal(GreedyPolicy(vf).control(x, 1.0), u_star)


def test_at_a_kink_the_greedy_input_commits_where_the_gradient_does_not():
    """V = |a - b| - 0.2 ties two manoeuvres on the diagonal: grad V there is 0, so u* is the box
    centre and V does not rise; the greedy input moves off the diagonal, raising V by 2 x step."""
    system = _Plane()
    vf = _Analytic(system, lambda x: (x[..., 0] - x[..., 1]).abs() - 0.2)
    x = torch.tensor([[0.3, 0.3], [-0.4, -0.4]])
    u_star = OptimalPolicy(vf).control(x, 1.0)
    u_greedy = GreedyPolicy(vf).control(x, 1.0)
    v_star = vf.value(_after_step(system, x, u_star), 1.0)
    v_greedy = vf.value(_after_step(system, x, u_greedy), 1.0)
    assert torch.allclose(v_star, vf.value(x, 1.0))
    assert torch.all(v_greedy > v_star + 1.5 * GREEDY_STEP)


class _OpenPlane(_Plane):
    """The plane with danger only far outside the domain (l > 0 within radius sqrt(10))."""

    def failure_margin_columns(self, x, xp):
        return 10.0 - x[0] ** 2 - x[1] ** 2


def test_beyond_the_domain_the_greedy_input_still_reads_v():
    """A held step may leave the domain; V is read there as u* reads grad V (a network extrapolates,
    a grid takes its edge value), not replaced by l, whose one-step gain would steer instead."""
    system = _OpenPlane()
    vf = _Analytic(system, lambda x: x[..., 0] - 2 * x[..., 1])
    x = torch.tensor([[0.99, -0.99], [-0.99, 0.99]])
    assert torch.equal(GreedyPolicy(vf).control(x, 1.0), OptimalPolicy(vf).control(x, 1.0))


def test_the_greedy_input_avoids_a_step_through_the_failure_set():
    """It scores min(V after the step, l along it): a candidate whose held step leaves the domain's
    safe disc loses even where V after it would be large."""
    system = _Plane()
    vf = _Analytic(system, lambda x: x[..., 0])  # V rewards moving right; l forbids |x| > 0.9
    x = torch.tensor([[0.88, 0.0]])
    u = GreedyPolicy(vf).control(x, 1.0)
    assert system.failure_margin(_after_step(system, x, u)) > 0
    assert OptimalPolicy(vf).control(x, 1.0)[0, 0] == 1.0  # u* would push through it


def test_the_greedy_policy_refuses_what_it_cannot_trust():
    system = _Plane()
    vf = _Analytic(system, lambda x: x[..., 0] / (x[..., 1] - x[..., 1]))  # NaN or inf everywhere
    with pytest.raises(ValueError, match="non-finite"):
        GreedyPolicy(vf).control(torch.tensor([[0.1, 0.2]]), 1.0)
    good = _Analytic(system, lambda x: x[..., 0])
    for bad in (0.0, -0.05, float("nan"), True):
        with pytest.raises(ValueError, match="step"):
            GreedyPolicy(good, step=bad)


@pytest.mark.parametrize(
    "make",
    [
        lambda vf: rollout(vf, torch.zeros(1, 2), policy="greedyy", progress=False),
        lambda vf: VerifySettings(policy="greedyy"),
        lambda vf: SafetyFilter(vf, policy="greedyy"),
        lambda vf: FilterConfig("x", vf, policy="greedyy"),
    ],
)
def test_an_unknown_policy_is_refused_by_name_before_any_work(make):
    vf = _Analytic(_Plane(), lambda x: x[..., 0])
    with pytest.raises(ValueError, match="greedyy"):
        make(vf)


def test_rollouts_follow_the_chosen_policy():
    """From the kink, u* (the centre) never moves, the greedy policy does; both end safe here."""
    system = _Plane()
    vf = _Analytic(system, lambda x: (x[..., 0] - x[..., 1]).abs() - 0.2)
    x = torch.tensor([[0.3, 0.3]])
    still = rollout(vf, x, horizon=0.1, policy="gradient", record=True, progress=False).trajectories
    moved = rollout(vf, x, horizon=0.1, policy="greedy", record=True, progress=False).trajectories
    assert torch.equal(still[-1], x)
    assert (moved[-1, 0, 0] - moved[-1, 0, 1]).abs() > 0.1


def test_the_switch_with_the_greedy_input_keeps_the_three_car_merge_within_issue_18s_aim():
    """The shipped 9D model's switch in the three-car merge (500 starts outside its BRT, default
    threshold): with u* more than 1 % of episodes collide, three cars turning into each other where
    grad V blends turning left and right; the greedy input commits to one and keeps it within 1 %."""
    vf = load_value_function("pretrained:multivehicle9d").value_function
    from reach_envs.scenes import make_scene

    scene = make_scene("three-car-merge")
    starts = outside_states(vf, 500, 0.1, 0, scene)
    rows = evaluate_filters(
        scene,
        [FilterConfig("gradient", vf, policy="gradient"), FilterConfig("greedy", vf, policy="greedy")],
        episodes=500,
        initial_states=starts,
    )
    gradient, greedy = (r["collision_rate"] for r in rows)
    assert greedy <= 0.01 < gradient
    assert np.isclose(rows[0]["threshold"], rows[1]["threshold"])
