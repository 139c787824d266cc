"""The box training draws its points from (``ControlAffineSystem.training_domain``, issue 63 item 3).

A state's value comes from where its trajectory goes. The vertical drone with a gain below gravity
falls whatever it does and leaves its box through ``v = -4`` while still above the floor, so a
network trained on the box alone was free to call such states safe. Its training box must hold
every best-against-the-floor trajectory from the box until that trajectory meets the floor, and the
grid solver solves the box on the wider nodes instead of extrapolating at ``v = -4``. Its value also
falls up to about 9 units below ``l`` within the horizon, which a network whose output scale is the
margin's unit does not reach in a run: the system declares its scale (``value_scale``).
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from groundtruth.grid import Grid
from groundtruth.solver import solve
from reach.systems import Air3D, ParameterizedVertDrone2D
from training.config import TrainConfig
from training.sampling import PointSampler, training_box
from training.trainer import build_network


def _lowest_speed_above_floor(system: ParameterizedVertDrone2D, x: torch.Tensor) -> torch.Tensor:
    """Per state, the lowest speed of its full-thrust-up trajectory (the highest of all inputs at every
    time) before it meets the floor or the horizon ends, in closed form."""
    v, z, k = x.double().unbind(-1)
    accel = k * system.input_magnitude_max - system.gravity
    # first time z + v s + accel s^2 / 2 = 0 for s >= 0 (only a falling drone meets the floor)
    disc = (v**2 - 2 * accel * z).clamp_min(0.0)
    safe_accel = torch.where(accel.abs() < 1e-12, torch.full_like(accel, -1e-12), accel)
    root = (-v - torch.sqrt(disc)) / safe_accel
    meets = (disc > 0) & (root >= 0)
    end = torch.where(meets, root.clamp(max=system.horizon), torch.full_like(v, system.horizon))
    return torch.minimum(v, v + accel * end)  # speed is monotone in time along one input


def _box_states(system: ParameterizedVertDrone2D, n: int, seed: int) -> torch.Tensor:
    x = system.sample_states(n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    corners = torch.tensor([[-4.0, 3.5, 0.0], [-4.0, 3.0, 0.0], [0.0, 3.0, 0.0]], dtype=torch.float64)
    return torch.cat([x[x[:, 1] > 0], corners])


def test_the_drones_box_is_left_above_the_floor_so_training_needs_more() -> None:
    """Against a plain domain, the check below fails: the falling drone's speed leaves it."""
    system = ParameterizedVertDrone2D()
    lowest = _lowest_speed_above_floor(system, _box_states(system, 20_000, 0))
    assert float((lowest < system.domain[0][0]).double().mean()) > 0.1


@settings(max_examples=25, deadline=None)
@given(
    gravity=st.floats(1.0, 20.0),
    gain=st.floats(1.0, 30.0),
    magnitude=st.floats(0.1, 3.0),
    horizon=st.floats(0.2, 2.0),
)
def test_the_drones_training_box_holds_every_fall_until_the_floor(
    gravity: float, gain: float, magnitude: float, horizon: float
) -> None:
    system = ParameterizedVertDrone2D(
        gravity=gravity, input_multiplier_max=gain, input_magnitude_max=magnitude, horizon=horizon
    )
    (v_low, v_high), *rest = training_box(system)
    assert tuple(rest) == tuple(system.domain[1:]) and v_high == system.domain[0][1]
    lowest = _lowest_speed_above_floor(system, _box_states(system, 4000, 1))
    assert float(lowest.min()) >= v_low - 1e-9
    # no wider than the fastest such fall needs: from the top of the box with no thrust
    assert v_low >= -math.sqrt(4.0**2 + 2 * gravity * 3.5) - 1e-9


def test_points_are_drawn_from_the_training_box() -> None:
    config = TrainConfig(system="parameterizedvertdrone2d", steps=1, points=20_000)
    network = build_network(config)
    x, _ = PointSampler(config, network, torch.device("cpu")).uniform(20_000, 1.0)
    box = torch.tensor(network.system.training_domain(), dtype=x.dtype)
    assert bool(((x >= box[:, 0]) & (x <= box[:, 1])).all())
    assert float(x[:, 0].min()) < -8.0  # the widened speed range is sampled, not just allowed
    assert float((x[:, 0] < -4.0).double().mean()) == pytest.approx((9.2 - 4.0) / 13.2, abs=0.02)


def test_systems_without_a_training_domain_train_on_their_domain() -> None:
    config = TrainConfig(system="air3d", steps=1, points=4096)
    network = build_network(config)
    x, _ = PointSampler(config, network, torch.device("cpu")).uniform(4096, 1.0)
    box = torch.tensor(Air3D().domain, dtype=x.dtype)
    assert training_box(Air3D()) == tuple(tuple(b) for b in Air3D().domain)
    assert bool(((x >= box[:, 0]) & (x <= box[:, 1])).all())


class _Narrow(ParameterizedVertDrone2D):
    def training_domain(self) -> tuple[tuple[float, float], ...]:
        return ((-3.0, 4.0), *self.domain[1:])


class _Periodic(Air3D):
    def training_domain(self) -> tuple[tuple[float, float], ...]:
        return (*self.domain[:2], (-4.0, 4.0))


class _NaN(ParameterizedVertDrone2D):
    def training_domain(self) -> tuple[tuple[float, float], ...]:
        return ((math.nan, 4.0), *self.domain[1:])


@pytest.mark.parametrize(
    ("system", "match"),
    [
        (_Narrow(), r"training_domain of v must be finite and contain the domain \[-4.0, 4.0\], got \[-3.0, 4.0\]"),
        (_NaN(), r"training_domain of v must be finite .* got \[nan, 4.0\]"),
        (_Periodic(), r"periodic .* trains on its period"),
    ],
)
def test_a_training_box_that_leaves_out_the_domain_is_refused(system: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        training_box(system)


def _value_upper_bound(system: ParameterizedVertDrone2D, x: torch.Tensor) -> torch.Tensor:
    """``V <= min(min_s z+(s), min_s 3 - z-(s))``: full thrust up (down) is at least as high (at most as
    high) at every time as any other input, so no input does better against the floor (ceiling)."""
    v, z, k = x.double().unbind(-1)
    bounds = []
    for accel, floor_side in ((k - system.gravity, True), (-k - system.gravity, False)):
        vertex = (-v / torch.where(accel.abs() < 1e-12, torch.full_like(accel, 1e-12), accel)).clamp(0, system.horizon)
        times = torch.stack([torch.zeros_like(v), torch.full_like(v, system.horizon), vertex])
        height = z + v * times + 0.5 * accel * times**2
        bounds.append((height if floor_side else 3.0 - height).min(0).values)
    return torch.minimum(bounds[0], bounds[1])


def test_the_grid_solves_the_drones_box_on_its_training_domain() -> None:
    """Against the box alone (the edge's ghost nodes extrapolated), the grid rose above the closed-form
    bound by up to a metre and called safe states that provably reach the floor."""
    system = ParameterizedVertDrone2D()
    shape = (41, 41, 5)  # k has no dynamics: few nodes along it suffice
    solution = solve(system, shape, [0.0, 1.0], progress=False)
    assert solution.grid == Grid.for_system(system, shape)  # reported on the domain's nodes
    solved_on = solution.metadata["scheme"]["solved_on"]
    assert solved_on["low"][0] <= training_box(system)[0][0] and solved_on["shape"][1:] == shape[1:]
    x = solution.grid.points(torch.float64).reshape(-1, 3)
    values, upper = solution.at(1.0).reshape(-1).double(), _value_upper_bound(system, x)
    assert float((values - upper).max()) < 0.05
    assert int(((values > 0) & (upper <= -0.05)).sum()) == 0
    # the same nodes of the wide solve, to round-off: the cut keeps node positions
    wide = Grid(tuple(solved_on["low"]), tuple(solved_on["high"]), tuple(solved_on["shape"]), (False,) * 3)
    assert wide.spacing == pytest.approx(solution.grid.spacing)


def test_a_grid_given_as_a_grid_is_solved_as_given() -> None:
    system = ParameterizedVertDrone2D()
    grid = Grid.for_system(system, (21, 21, 5))
    solution = solve(system, grid, [0.0, 0.2], progress=False)
    assert "solved_on" not in solution.metadata["scheme"] and solution.grid == grid
    assert "solved_on" not in solve("air3d", 21, [0.0, 0.1], progress=False).metadata["scheme"]


def _lower_bound_hover(system: ParameterizedVertDrone2D, x: torch.Tensor) -> torch.Tensor:
    """``min_s l(z(s))`` under ``u = min(u_max, gravity / k)`` throughout, on a fine time grid: a value
    one input achieves, so a lower bound of ``V``."""
    v, z, k = x.double().unbind(-1)
    u = torch.minimum(torch.full_like(k, system.input_magnitude_max), system.gravity / k.clamp_min(1e-12))
    s = torch.linspace(0.0, system.horizon, 401, dtype=torch.float64)[:, None]
    height = z + v * s + 0.5 * (k * u - system.gravity) * s**2
    return torch.minimum(height, 3.0 - height).min(0).values


@settings(max_examples=25, deadline=None)
@given(
    gravity=st.floats(1.0, 20.0),
    gain=st.floats(1.0, 30.0),
    magnitude=st.floats(0.1, 3.0),
    horizon=st.floats(0.2, 2.0),
)
def test_the_drones_value_scale_bounds_how_far_the_value_falls(
    gravity: float, gain: float, magnitude: float, horizon: float
) -> None:
    system = ParameterizedVertDrone2D(
        gravity=gravity, input_multiplier_max=gain, input_magnitude_max=magnitude, horizon=horizon
    )
    x = system.sample_states(4000, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    margin = system.failure_margin(x).double()
    # V >= what hovering (or thrusting up) achieves >= l - scale: the scale covers every fall
    assert float((_lower_bound_hover(system, x) - margin).min()) >= -system.value_scale() - 1e-9
    # and is not loose: some state's value provably falls most of the way (V <= the closed-form bound)
    assert float((margin - _value_upper_bound(system, x)).max()) >= 0.5 * system.value_scale()


def test_training_starts_from_the_systems_value_scale() -> None:
    """With the margin's unit as the scale (the default before), the drone's value lay out of reach:
    it falls more than 8 units below ``l`` within the horizon."""
    system = ParameterizedVertDrone2D()
    x = _box_states(system, 20_000, 3)
    deepest_fall = float((system.failure_margin(x).double() - _value_upper_bound(system, x)).max())
    network = build_network(TrainConfig(system="parameterizedvertdrone2d", steps=1))
    assert deepest_fall > 8.0
    assert network.encoding.value_scale == system.value_scale() >= deepest_fall
    assert build_network(TrainConfig(system="air3d", steps=1)).encoding.value_scale == 1.0
    chosen = TrainConfig(system="parameterizedvertdrone2d", steps=1, value_scale=2.5)
    assert build_network(chosen).encoding.value_scale == 2.5


def test_a_non_positive_value_scale_is_refused() -> None:
    with pytest.raises(ValueError, match="value_scale"):
        TrainConfig(system="parameterizedvertdrone2d", steps=1, value_scale=0.0).validate()
