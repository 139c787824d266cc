"""Interval arithmetic as a column backend (safety.formal.intervals): every system's physics, bounded soundly.

For every registered system, on random boxes of states (from nearly points to a tenth of the domain),
the interval drift-plus-inputs, margins and whole Euler and RK4 steps must contain the values the
torch backend computes at states sampled in the boxes, with the disturbance sampled in its box.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from reach.integrators import make_stepper
from reach.systems import SYSTEMS
from reach.systems.arrays import TORCH
from safety.formal.intervals import INTERVAL, Interval, box_columns


def _constructible(name: str) -> bool:
    try:
        SYSTEMS[name]()
    except TypeError:  # a generic family (multivehicle needs its cars): its registered members are tested
        return False
    return True


NAMES = [name for name in sorted(SYSTEMS) if _constructible(name)]

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import my_systems  # noqa: E402  (the user-written systems of the docs get every tool too)

USER_SYSTEMS = {
    f"user:{cls.__name__}": cls for cls in (my_systems.DubinsAvoid, my_systems.DubinsAccel, my_systems.DubinsGap)
}


def _uniform(g: torch.Generator, lo: torch.Tensor, hi: torch.Tensor, n: int) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand((n, *lo.shape), generator=g, dtype=torch.float64)


def _case(name: str, seed: int, log_half_width: float, samples: int = 64):
    """A system, one box of states, a control point and the disturbance box, with samples inside."""
    system = (USER_SYSTEMS | SYSTEMS)[name]()
    g = torch.Generator().manual_seed(seed)
    domain = system.domain_tensor(torch.float64, "cpu")
    span = domain[:, 1] - domain[:, 0]
    centre = _uniform(g, domain[:, 0], domain[:, 1], 1)[0]
    half = span * 10.0**log_half_width * torch.rand(span.shape, generator=g, dtype=torch.float64)
    lo, hi = centre - half, centre + half
    x = _uniform(g, lo, hi, samples)
    x[:2] = torch.stack([lo, hi])  # the corners themselves
    box_u = system.control_bounds
    u = _uniform(g, torch.tensor(box_u.low, dtype=torch.float64), torch.tensor(box_u.high, dtype=torch.float64), 1)[0]
    if system.disturbance_dim:
        d_lo = torch.tensor(system.disturbance_bounds.low, dtype=torch.float64)
        d_hi = torch.tensor(system.disturbance_bounds.high, dtype=torch.float64)
    else:
        d_lo = d_hi = torch.zeros(0, dtype=torch.float64)
    d = _uniform(g, d_lo, d_hi, samples)
    return system, (lo, hi), u, (d_lo, d_hi), x, d


def _contains(bound: Interval, values: torch.Tensor) -> bool:
    return bool(((values >= bound.lo) & (values <= bound.hi)).all())


def _margins(system):
    names = ["failure_margin_columns"]
    if system.problem.has_target if hasattr(system.problem, "has_target") else system.kind != "avoid":
        names = ["target_margin_columns"]
    if system.problem.has_constraint:
        names.append("constraint_margin_columns")
    return [getattr(system, n) for n in names]


@pytest.mark.parametrize("name", NAMES + sorted(USER_SYSTEMS))
@settings(max_examples=8, deadline=None)
@given(st.integers(0, 10_000), st.floats(-4, -1))
def test_interval_physics_contains_every_sampled_value(name, seed, log_half_width):
    system, (lo, hi), u, (d_lo, d_hi), x, d = _case(name, seed, log_half_width)
    x_box = box_columns(lo.unsqueeze(0), hi.unsqueeze(0))
    u_cols = [Interval.point(v) for v in u.tolist()]
    d_box = box_columns(d_lo.unsqueeze(0), d_hi.unsqueeze(0)) if system.disturbance_dim else []
    x_cols, d_cols = TORCH.unbind(x), TORCH.unbind(d) if system.disturbance_dim else []
    u_t = [torch.full((len(x),), v, dtype=torch.float64) for v in u.tolist()]
    xdot = INTERVAL.stack(system.xdot_columns(x_box, u_cols, d_box, INTERVAL))
    exact = TORCH.stack(system.xdot_columns(x_cols, u_t, d_cols, TORCH))
    assert _contains(xdot, exact), "xdot"
    for margin in _margins(system):
        assert _contains(Interval.of(margin(x_box, INTERVAL)), margin(x_cols, TORCH)), margin.__name__
    for integrator in ("euler", "rk4"):
        step = make_stepper(system, 0.05, integrator, INTERVAL)(x_box, u_cols, d_box)
        exact = TORCH.stack(make_stepper(system, 0.05, integrator, TORCH)(x_cols, u_t, d_cols))
        assert _contains(INTERVAL.stack(step), exact), integrator


@settings(max_examples=200, deadline=None)
@given(
    st.floats(-10, 10),
    st.floats(0, 5),
    st.floats(-10, 10),
    st.floats(0, 5),
    st.sampled_from(["+", "-", "*", "/", "hypot", "atan2", "sqrt", "abs", "sq", "wrap", "min", "where"]),
)
def test_each_operation_contains_every_sampled_result(a, wa, b, wb, op):
    g = torch.Generator().manual_seed(0)
    x, y = Interval(a, a + wa), Interval(b, b + wb)
    xs = a + wa * torch.rand(300, generator=g, dtype=torch.float64)
    ys = b + wb * torch.rand(300, generator=g, dtype=torch.float64)
    xs[:2], ys[:2] = torch.tensor([a, a + wa], dtype=torch.float64), torch.tensor([b + wb, b], dtype=torch.float64)
    tiny = 1 / 1.7976931348623157e308  # below this magnitude 1 / b overflows, on either side of 0
    if op == "/" and (b <= 0 <= b + wb or min(abs(b), abs(b + wb)) < tiny):
        with pytest.raises(ZeroDivisionError):
            _ = x / y
        return
    cases = {
        "+": (lambda: x + y, xs + ys),
        "-": (lambda: x - y, xs - ys),
        "*": (lambda: x * y, xs * ys),
        "/": (lambda: x / y, xs / ys),
        "hypot": (lambda: INTERVAL.hypot(x, y), torch.hypot(xs, ys)),
        "atan2": (lambda: INTERVAL.atan2(y, x), torch.atan2(ys, xs)),
        "sqrt": (lambda: INTERVAL.sqrt(INTERVAL.abs(x)), torch.sqrt(xs.abs())),
        "abs": (lambda: INTERVAL.abs(x), xs.abs()),
        "sq": (lambda: x**2, xs**2),
        "wrap": (lambda: INTERVAL.wrap_angle(x), TORCH.wrap_angle(xs)),
        "min": (lambda: INTERVAL.minimum(x, y), torch.minimum(xs, ys)),
        "where": (lambda: INTERVAL.where(x > y, x, y), torch.where(xs > ys, xs, ys)),
    }
    bound, values = cases[op]
    assert _contains(bound(), values)
    assert math.isfinite(float(bound().lo)) and math.isfinite(float(bound().hi))


def test_an_interval_comparison_has_no_single_truth():
    with pytest.raises(TypeError, match="no single truth value"):
        bool(Interval(0.0, 1.0) > 0.5)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.floats(min_value=-1e12, max_value=1e12, allow_nan=False).filter(lambda v: v == 0 or abs(v) > 1e-100),
        min_size=2,
        max_size=2,
    ),
    st.sampled_from(["add", "mul"]),
)
def test_sums_and_products_are_rounded_outward_and_exact_ones_are_not_widened(pair, op):
    """The bounds of one float64 sum or product contain its exact real value (checked in rational
    arithmetic), are at most one ulp wide on each side (away from underflow, where a tiny absolute
    widening takes over), and an exact result is not widened at all:
    ``x + 0``, ``x * 0``, ``x * 1`` and ``x * 2`` stay points, so a box face that a step leaves in
    place stays exactly on its cell's edge."""
    from fractions import Fraction

    from safety.formal.intervals import _product_bounds, _sum_bounds

    a, b = (torch.tensor([v], dtype=torch.float64) for v in pair)
    bounds, exact = (
        (_sum_bounds(a, b), Fraction(pair[0]) + Fraction(pair[1]))
        if op == "add"
        else (_product_bounds(a, b), Fraction(pair[0]) * Fraction(pair[1]))
    )
    lo, hi = float(bounds[0]), float(bounds[1])
    assert Fraction(lo) <= exact <= Fraction(hi)
    assert hi <= math.nextafter(math.nextafter(lo, math.inf), math.inf)
    exact_ones = [_sum_bounds(a, torch.zeros(1, dtype=torch.float64))]
    exact_ones += [_product_bounds(a, torch.tensor([k], dtype=torch.float64)) for k in (0.0, 1.0, 2.0)]
    for low, high in exact_ones:
        assert float(low) == float(high)
