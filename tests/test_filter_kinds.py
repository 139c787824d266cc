"""Safety filters for reach kinds: one implementation, read through ``problem.orient``.

Toy systems with exact values: a point on a line, ``x' = u`` with ``|u| <= 1``, must reach the target
``|x - 1| < 0.2`` (reach), also keeping ``x > -0.5`` (reach-avoid). Its reach-avoid value (exact for
``x <= 1``) is ``V(x, t) = max(|x - 1| - 0.2 - t, -(x + 0.5))``: the time to the target less the
time-to-go, or the obstacle's margin where that is worse; ``u* = +1`` heads for the target.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from reach.systems.base import ControlAffineSystem
from reach.systems.box import Box
from safety.filters.base import SafetyFilter
from safety.filters.settings import REMAINING, FilterSettings
from safety.filters.wrappers import _Adapter

DT = 0.1


class _Line(ControlAffineSystem):
    """``x' = u`` on [-2, 2]: reach the target ``|x - 1| < 0.2`` within 2 s."""

    name = "line"
    kind = "reach"
    state_names = ("x",)
    periodic = (False,)
    domain = ((-2.0, 2.0),)
    control_bounds = Box.symmetric([1.0])
    horizon = 2.0

    def drift(self, x, xp):
        return [0.0 * x[0]]

    def control_matrix(self, x, xp):
        return {(0, 0): 1.0}

    def target_margin_columns(self, x, xp):
        return xp.abs(x[0] - 1.0) - 0.2


class _Corridor(_Line):
    """The line with an obstacle at ``x <= -0.5``: reach-avoid."""

    name = "corridor"
    kind = "reach-avoid"

    def constraint_margin_columns(self, x, xp):
        return x[0] + 0.5

    def margin_rate_bound(self):
        return 1.0  # |x'| <= 1: the env adapters' default threshold is 2 * 1 * dt


class _Cliff(_Line):
    """The line as an avoid problem: stay out of ``x <= -0.5``."""

    name = "cliff"
    kind = "avoid"
    target_margin_columns = ControlAffineSystem.target_margin_columns  # the line's target: none for avoid

    def failure_margin_columns(self, x, xp):
        return x[0] + 0.5


class _Value:
    """A value function from a formula ``V(x, t)`` (gradient by autograd); ``nan_where(x)`` poisons
    the value (``"value"``) or the gradient (``"gradient"``) there."""

    def __init__(self, system, formula, nan_where=None, poison="value"):
        self.system, self.formula, self.nan_where, self.poison = system, formula, nan_where, poison

    def _t(self, x, t):
        return torch.as_tensor(t, dtype=x.dtype).reshape(torch.as_tensor(t).shape or ())

    def value(self, x, t):
        v = self.formula(x[..., 0], self._t(x, t))
        if self.nan_where is not None and self.poison == "value":
            v = torch.where(self.nan_where(x[..., 0]), math.nan, v)
        return v

    def gradient(self, x, t):
        with torch.enable_grad():
            xg = x.detach().clone().requires_grad_(True)
            (p,) = torch.autograd.grad(self.formula(xg[..., 0], self._t(x, t)).sum(), xg)
        if self.nan_where is not None and self.poison == "gradient":
            p = torch.where(self.nan_where(x[..., 0]).unsqueeze(-1), math.nan, p)
        return p


def _reach_avoid_value(x, t):
    return torch.maximum((x - 1).abs() - 0.2 - t, -(x + 0.5))


def _corridor(**kwargs) -> _Value:
    return _Value(_Corridor(), _reach_avoid_value, **kwargs)


def _states(*xs: float) -> torch.Tensor:
    return torch.tensor(xs, dtype=torch.float64).unsqueeze(-1)


def test_the_switch_keeps_the_nominal_input_deep_inside_and_applies_the_minimising_u_star_near_the_edge():
    vf = _corridor()
    system = vf.system
    # V(0, 1.5) = -0.5 (deep inside), V(0, 0.85) = -0.05 (inside, but within the threshold of 0.1),
    # V(-0.45, 2) = -0.05 (the obstacle's margin decides), V(0, 0.5) = +0.3 (the task is infeasible)
    x = _states(0.0, 0.0, -0.45, 0.0)
    t = torch.tensor([1.5, 0.85, 2.0, 0.5], dtype=torch.float64)
    nominal = torch.zeros(4, 1, dtype=torch.float64)
    u, info = SafetyFilter(vf, 0.1, kind="switch", system=system)(x, t, nominal)
    assert info.intervened.tolist() == [False, True, True, True]
    torch.testing.assert_close(info.value, _reach_avoid_value(x[:, 0], t))  # V itself, not oriented
    assert torch.equal(u[0], nominal[0])
    # u* minimises V: +1, toward the target (and away from the obstacle)
    u_star = system.optimal_control(x, vf.gradient(x, t))
    assert torch.equal(u[1:], u_star[1:]) and torch.equal(u[1:], torch.ones(3, 1, dtype=torch.float64))
    # the same decisions as the avoid filter's on -V: one rule, oriented (keep where -V > threshold)
    assert torch.equal(~info.intervened, system.problem.orient(info.value) > 0.1)


def test_a_reach_problem_without_a_constraint_filters_the_same_way():
    vf = _Value(_Line(), lambda x, t: (x - 1).abs() - 0.2 - t)
    x = _states(0.0, 0.0)
    u, info = SafetyFilter(vf, 0.1, kind="lookahead", dt=DT)(x, torch.tensor([1.5, 0.85]), torch.zeros(2, 1))
    assert info.intervened.tolist() == [False, True] and float(u[1, 0]) == 1.0


def test_the_lookahead_judges_the_next_state_at_the_counted_down_time_to_go():
    vf = _corridor()
    filt = SafetyFilter(vf, 0.15, kind="lookahead", dt=DT, backup_horizon=0.0)
    switch = SafetyFilter(vf, 0.15, kind="switch")
    # from x = 0 at t = 1 (V = -0.2): stopping (u = 0) leaves V(0, 0.9) = -0.1, above -0.15: a held
    # time-to-go would have kept it; driving on (u = +1) keeps V(0.1, 0.9) = -0.2.
    # from x = -0.3 at t = 2 (V = -0.2, the obstacle's margin): backing off (u = -1) reaches
    # x = -0.4, V = -0.1; the switch, deciding on the current state, keeps both.
    x = _states(0.0, 0.0, -0.3)
    nominal = torch.tensor([[0.0], [1.0], [-1.0]], dtype=torch.float64)
    t = torch.tensor([1.0, 1.0, 2.0], dtype=torch.float64)
    u, info = filt(x, t, nominal)
    assert info.intervened.tolist() == [True, False, True]
    assert torch.equal(u, torch.tensor([[1.0], [1.0], [1.0]], dtype=torch.float64))
    assert not switch(x, t, nominal)[1].intervened.any()


def test_the_lookahead_rolls_u_star_to_the_target_and_checks_the_constraint_margin_on_the_way():
    filt = SafetyFilter(_corridor(), 0.15, kind="lookahead", dt=DT)  # backup rollout: the 2 s horizon
    assert filt.backup_steps == 20
    # driving on from x = 0 at t = 1: u* then reaches the target at x = 0.9 with V = -0.2 throughout
    _, info = filt(_states(0.0), 1.0, torch.ones(1, 1, dtype=torch.float64))
    assert not info.intervened.any()
    # a value function that claims every state (V = -1) is not trusted inside the obstacle (g < 0)
    # nor outside the domain: min(-V, g) and -inf there decide
    liar = _Value(_Corridor(), lambda x, t: 0.0 * x - 1.0)
    x = _states(-0.45, 0.5)
    nominal = torch.tensor([[-1.0], [1.0]], dtype=torch.float64)
    _, info = SafetyFilter(liar, 0.0, kind="lookahead", dt=DT, backup_horizon=0.0)(x, 1.0, nominal)
    assert info.intervened.tolist() == [True, False]
    line_liar = _Value(_Line(), lambda x, t: 0.0 * x - 1.0)
    _, info = SafetyFilter(line_liar, 0.0, kind="lookahead", dt=DT, backup_horizon=0.0)(
        _states(-1.95, 0.0), 1.0, torch.tensor([[-1.0], [-1.0]])
    )
    assert info.intervened.tolist() == [True, False]  # -2.05 lies outside the domain [-2, 2]


def test_when_the_time_to_go_runs_out_the_filter_applies_u_star():
    vf = _corridor()
    x = _states(0.95, 0.95)  # in the target: V(0.95, t) = -0.25 - t
    nominal = torch.zeros(2, 1, dtype=torch.float64)
    _, info = SafetyFilter(vf, 0.1, kind="switch")(x, torch.tensor([0.5, 0.0]), nominal)
    assert info.intervened.tolist() == [False, True]
    u, info = SafetyFilter(vf, 0.1, kind="lookahead", dt=DT)(x, torch.tensor([DT, 0.05]), nominal)
    assert info.intervened.tolist() == [False, True] and float(u[1, 0]) == 1.0


@pytest.mark.parametrize("kind", ["switch", "lookahead"])
@pytest.mark.parametrize("poison", ["value", "gradient"])
def test_non_finite_values_or_gradients_raise_instead_of_passing_the_nominal_input(kind, poison):
    vf = _corridor(nan_where=lambda x: x > 0.5, poison=poison)
    filt = SafetyFilter(vf, 0.0, kind=kind, dt=DT)
    nominal = torch.ones(2, 1, dtype=torch.float64)
    with pytest.raises(ValueError, match="non-finite"):
        filt(_states(0.0, 0.6), 1.0, nominal)
    if kind == "lookahead" and poison == "value":  # a NaN met one step ahead, in the prediction
        with pytest.raises(ValueError, match="non-finite"):
            filt(_states(0.45), 1.0, nominal[:1])


def test_a_value_function_of_another_kind_is_refused_naming_both_kinds():
    avoid_vf = _Value(_Cliff(), lambda x, t: x + 0.5)
    with pytest.raises(ValueError, match=r"of kind 'avoid' .*serves one of kind 'reach-avoid'"):
        SafetyFilter(avoid_vf, system=_Corridor())
    with pytest.raises(ValueError, match=r"of kind 'reach-avoid' .*serves one of kind 'avoid'"):
        SafetyFilter(_corridor(), system=_Cliff())
    with pytest.raises(ValueError, match=r"of kind 'reach' .*serves one of kind 'reach-avoid'"):
        SafetyFilter(_Value(_Line(), lambda x, t: x), system=_Corridor())
    scene = SimpleNamespace(episode_horizon=2.0, dt=DT, integrator="rk4")
    with pytest.raises(ValueError, match=r"of kind 'avoid' .*serves one of kind 'reach-avoid'"):
        _Adapter(_Corridor(), avoid_vf, scene, "cpu", FilterSettings())


def test_settings_a_reach_kind_cannot_use_are_refused_naming_the_kind():
    vf = _corridor()
    with pytest.raises(ValueError, match="smooth filter serves avoid problems only; corridor is a reach-avoid"):
        SafetyFilter(vf, kind="smooth")
    with pytest.raises(ValueError, match=r"policy='greedy' .* corridor is a reach-avoid problem"):
        SafetyFilter(vf, kind="switch", policy="greedy")
    with pytest.raises(ValueError, match=r"time_to_go=1\.0 holds the time-to-go fixed"):
        SafetyFilter(vf, time_to_go=1.0)
    # the switch's default backup input (greedy for avoid) is u* for reach kinds
    filt = SafetyFilter(vf, kind="switch")
    assert filt.greedy is None and filt.settings.backup_policy == "gradient"
    assert SafetyFilter(_Value(_Cliff(), lambda x, t: x + 0.5), kind="switch").settings.backup_policy == "greedy"


def test_the_env_adapter_counts_the_time_to_go_down_for_reach_kinds_only():
    scene = SimpleNamespace(episode_horizon=2.0, dt=DT, integrator="rk4")
    adapter = _Adapter(_Corridor(), _corridor(), scene, "cpu", FilterSettings())
    assert adapter.time_to_go == REMAINING and adapter.filter.threshold == pytest.approx(2 * DT)
    assert float(adapter.times(0.5)) == 1.5 and float(adapter.times(2.5)) == 0.0
    torch.testing.assert_close(adapter.times([0.0, 1.25]), torch.tensor([2.0, 0.75], dtype=torch.float64))
    with pytest.raises(ValueError, match="holds the time-to-go fixed"):
        _Adapter(_Corridor(), _corridor(), scene, "cpu", FilterSettings(time_to_go=1.0))
    # no declared rate bound: the default threshold samples the target margin's rate (|x'| <= 1 here)
    sampled = _Adapter(_Line(), _Value(_Line(), lambda x, t: x), scene, "cpu", FilterSettings())
    assert sampled.filter.threshold == pytest.approx(2 * 1.0 * DT)
    line = _Adapter(_Line(), _Value(_Line(), lambda x, t: x), scene, "cpu", FilterSettings(threshold=0.05))
    assert float(line.times(0.5)) == 1.5
    avoid = _Adapter(_Cliff(), _Value(_Cliff(), lambda x, t: x + 0.5), scene, "cpu", FilterSettings())
    assert avoid.time_to_go is None and avoid.times(0.5) == 2.0  # avoid: the fixed horizon, as before


def test_the_avoid_lookahead_still_holds_the_time_to_go():
    """Avoid's tube value only falls as t grows: its lookahead keeps evaluating at t itself."""
    vf = _Value(_Cliff(), lambda x, t: x + 0.5 - 0.5 * t)  # V(0, 1) = 0, V(0, 0.9) = 0.05
    _, info = SafetyFilter(vf, 0.01, kind="lookahead", dt=DT, backup_horizon=0.0)(
        _states(0.0), 1.0, torch.zeros(1, 1, dtype=torch.float64)
    )
    assert info.intervened.tolist() == [True]
