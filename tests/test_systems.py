"""Systems: derived Hamiltonian and optimal inputs against brute force, geometry, margins, wrapping."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

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
    MultiVehicle12D,
    MultiVehicle15D,
    make_system,
    system_from_config,
)

SYSTEMS = [
    Air3D(),
    MultiVehicle6D(),
    MultiVehicle9D(),
    MultiVehicle12D(),  # the N-car family: four and five cooperating cars
    MultiVehicle15D(),
    # two pursuers with different limits and an evader: asymmetric boxes and both players present
    MultiVehicle([Car(0.5, 2.0, "control"), Car(0.7, 1.5, "disturbance"), Car(0.4, 0.5, "disturbance")]),
    # the reach kinds: the control minimises, the disturbance (the wind) maximises
    Dubins3D("reach"),
    DubinsReachAvoid(),
]


def _random_states(system, n, gen, dtype=torch.float64):
    x = system.sample_states(n, generator=gen, dtype=dtype)
    return x * 1.3  # also outside the domain: the formulas must hold everywhere


def _input_grid(box, points):
    axes = [np.linspace(lo, hi, points) for lo, hi in zip(box.low, box.high)]
    if not axes:
        return torch.zeros(1, 0, dtype=torch.float64)
    return torch.tensor(list(itertools.product(*axes)), dtype=torch.float64)


@pytest.mark.parametrize("system", SYSTEMS, ids=lambda s: s.name + str(s.state_dim))
def test_hamiltonian_equals_brute_force_max_min(system):
    gen = torch.Generator().manual_seed(0)
    n = 16
    x = _random_states(system, n, gen)
    p = torch.randn(n, system.state_dim, generator=gen, dtype=torch.float64)
    points = 21 if system.control_dim + system.disturbance_dim <= 2 else 9
    U = _input_grid(system.control_bounds, points)
    D = _input_grid(system.disturbance_bounds, points)
    # p . f(x, u, d) for every (state, u, d): shape (n, |U|, |D|)
    xs = x[:, None, None, :].expand(n, len(U), len(D), system.state_dim)
    us = U[None, :, None, :].expand(n, len(U), len(D), U.shape[1])
    ds = D[None, None, :, :].expand(n, len(U), len(D), D.shape[1])
    f = system.dynamics(xs, us, ds if system.disturbance_dim else None)
    pf = (p[:, None, None, :] * f).sum(-1)
    inner = pf.min(dim=2).values if system.disturbance_objective == "min" else pf.max(dim=2).values
    brute = inner.max(dim=1).values if system.control_objective == "max" else inner.min(dim=1).values
    torch.testing.assert_close(system.hamiltonian(x, p), brute, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("system", SYSTEMS, ids=lambda s: s.name + str(s.state_dim))
@pytest.mark.parametrize("grad", [True, False], ids=["autograd", "no-grad"])
def test_hamiltonian_at_fixed_states_with_scale_and_pruning_is_the_hamiltonian(system, grad):
    """The grid solver's form of H (coefficients evaluated once, zero entries pruned, a factor per
    costate component folded in, accumulated in place without autograd) equals ``hamiltonian``, and
    never writes into the caller's costate columns; on torch and NumPy columns."""
    gen = torch.Generator().manual_seed(1)
    x = _random_states(system, 64, gen)
    p = torch.randn(64, system.state_dim, generator=gen, dtype=torch.float64)
    scale = [(-1.0) ** i * (0.5 + i) for i in range(system.state_dim)]
    want = system.hamiltonian(x, p)
    with torch.set_grad_enabled(grad):
        cols = [c.clone() for c in TORCH.unbind(p / torch.tensor(scale, dtype=torch.float64))]
        before = [c.clone() for c in cols]
        h = system.hamiltonian_at(TORCH.unbind(x), TORCH, scale=scale, prune=True)(cols)
    torch.testing.assert_close(h, want, rtol=1e-12, atol=1e-12)
    for c, b in zip(cols, before):
        assert torch.equal(c, b)
    h_np = system.hamiltonian_at(NUMPY.unbind(x.numpy()), NUMPY, scale=scale, prune=True)(
        NUMPY.unbind((p / torch.tensor(scale, dtype=torch.float64)).numpy())
    )
    np.testing.assert_allclose(h_np, want.numpy(), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "scale, message",
    [([1.0, 1.0], "2 factors for 3"), ([1.0, float("nan"), 1.0], "nan"), ([1.0, 0.0, 1.0], "got 0.0")],
)
def test_hamiltonian_at_refuses_a_bad_scale(scale, message):
    """A wrong count, a NaN or a zero factor is refused with the bad value named, before any H."""
    system = Air3D()
    x = TORCH.unbind(torch.zeros(4, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=message):
        system.hamiltonian_at(x, TORCH, scale=scale)


@pytest.mark.parametrize("system", SYSTEMS, ids=lambda s: s.name + str(s.state_dim))
def test_optimal_inputs_attain_the_hamiltonian(system):
    gen = torch.Generator().manual_seed(1)
    x = _random_states(system, 64, gen)
    p = torch.randn(64, system.state_dim, generator=gen, dtype=torch.float64)
    u = system.optimal_control(x, p)
    d = system.optimal_disturbance(x, p)
    assert u.shape == (64, system.control_dim) and d.shape == (64, system.disturbance_dim)
    f = system.dynamics(x, u, d if system.disturbance_dim else None)
    torch.testing.assert_close((p * f).sum(-1), system.hamiltonian(x, p), rtol=1e-12, atol=1e-12)


def test_air3d_matches_reference_formulas():
    s = Air3D()
    gen = torch.Generator().manual_seed(2)
    x = _random_states(s, 100, gen)
    p = torch.randn(100, 3, generator=gen, dtype=torch.float64)
    x1, x2, x3 = x.unbind(-1)
    p1, p2, p3 = p.unbind(-1)
    switch = p1 * x2 - p2 * x1 - p3
    H = -0.75 * p1 + 0.75 * (p1 * torch.cos(x3) + p2 * torch.sin(x3)) + 3 * switch.abs() - 3 * p3.abs()
    torch.testing.assert_close(s.hamiltonian(x, p), H)
    torch.testing.assert_close(s.optimal_control(x, p)[:, 0], 3 * torch.sign(switch))
    torch.testing.assert_close(s.optimal_disturbance(x, p)[:, 0], -3 * torch.sign(p3))


def test_9d_matches_reference_formula():
    s = MultiVehicle9D()
    gen = torch.Generator().manual_seed(3)
    x = _random_states(s, 100, gen)
    p = torch.randn(100, 9, generator=gen, dtype=torch.float64)
    th = x[:, 6:]
    px, py, pth = p[:, 0:6:2], p[:, 1:6:2], p[:, 6:]
    H = (0.6 * (torch.cos(th) * px + torch.sin(th) * py) + 1.1 * pth.abs()).sum(-1)
    torch.testing.assert_close(s.hamiltonian(x, p), H)
    torch.testing.assert_close(s.optimal_control(x, p), 1.1 * torch.sign(pth))
    assert s.optimal_disturbance(x, p).shape == (100, 0)


def test_tie_break_is_box_centre_when_switching_function_is_zero():
    s = Air3D()
    # x at the origin with p3 = 0: both switching functions p1 x2 - p2 x1 - p3 and p3 vanish exactly
    x = torch.tensor([[0.0, 0.0, 0.7], [0.0, 0.0, -2.0]], dtype=torch.float64)
    p = torch.tensor([[1.0, -2.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.equal(s.optimal_control(x, p), torch.zeros(2, 1, dtype=torch.float64))
    assert torch.equal(s.optimal_disturbance(x, p), torch.zeros(2, 1, dtype=torch.float64))
    # an asymmetric box: the centre, not zero, is the tie-break
    mv = MultiVehicle([Car(0.5, 2.0, "control"), Car(0.5, 1.0, "control")])
    mv.control_bounds = type(mv.control_bounds)((-2.0, -1.0), (1.0, 1.0))
    u = mv.optimal_control(torch.zeros(1, 6), torch.zeros(1, 6))
    assert u.tolist() == [[-0.5, 0.0]]
    # the float and numpy backends use the same rule
    assert s.optimal_inputs_columns([0.0, 0.0, 0.3], [1.0, 1.0, 0.0], FLOAT) == ([0.0], [0.0])


@pytest.mark.parametrize("system", SYSTEMS, ids=lambda s: s.name + str(s.state_dim))
def test_dissipation_bounds_are_the_max_speed_per_dimension(system):
    gen = torch.Generator().manual_seed(4)
    x = _random_states(system, 32, gen)
    alpha = system.dissipation_bounds(x)
    # brute force over box corners (|xdot_i| is convex in the inputs, so corners attain its max)
    corners_u = _input_grid(system.control_bounds, 2)
    corners_d = _input_grid(system.disturbance_bounds, 2)
    best = torch.zeros_like(alpha)
    for u, d in itertools.product(corners_u, corners_d):
        f = system.dynamics(x, u.expand(32, -1), d.expand(32, -1) if system.disturbance_dim else None)
        best = torch.maximum(best, f.abs())
    torch.testing.assert_close(alpha, best, rtol=1e-12, atol=1e-12)
    # and it bounds |dH/dp| (autograd) at random costates
    p = torch.randn(32, system.state_dim, generator=gen, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(system.hamiltonian(x, p).sum(), p)
    assert (grad.abs() <= alpha + 1e-12).all()


def test_6d_projected_to_relative_coordinates_matches_air3d():
    six, air = MultiVehicle6D(), Air3D()
    rng = np.random.default_rng(5)
    dt = 1e-3
    step6 = make_stepper(six, dt, "rk4", FLOAT)
    step3 = make_stepper(air, dt, "rk4", FLOAT)
    for _ in range(3):
        x6 = [*rng.uniform(-1, 1, 4).tolist(), *rng.uniform(-math.pi, math.pi, 2).tolist()]
        x3 = six.relative_coordinates(x6, FLOAT)
        worst = 0.0
        for k in range(1100):
            if k % 50 == 0:  # piecewise-constant inputs, same for both systems
                u, d = [float(rng.uniform(-3, 3))], [float(rng.uniform(-3, 3))]
            x6, x3 = step6(x6, u, d), step3(x3, u, d)
            rel = six.relative_coordinates(x6, FLOAT)
            diff = [abs(a - b) for a, b in zip(rel[:2], x3[:2])] + [abs(FLOAT.wrap_angle(rel[2] - x3[2]))]
            worst = max(worst, *diff)
        assert worst < 1e-9, worst
        # failure margins agree too: the 6D collision is the Air3D collision
        assert abs(six.failure_margin_float(x6) - air.failure_margin_float(x3)) < 1e-9


def test_failure_margin_values_and_signs():
    air = Air3D()
    x = torch.tensor([[0.25, 0.0, 1.0], [0.0, 0.0, 0.0], [0.3, 0.4, -3.0], [0.1, 0.1, 2.0]], dtype=torch.float64)
    torch.testing.assert_close(
        air.failure_margin(x), torch.tensor([0.0, -0.25, 0.25, math.hypot(0.1, 0.1) - 0.25], dtype=torch.float64)
    )
    nine = MultiVehicle9D()
    # pairs: (1,2) at 0.3 apart, (1,3) and (2,3) far
    x9 = torch.tensor([[0.0, 0.0, 0.3, 0.0, 1.0, 1.0, 0.0, 1.0, 2.0]], dtype=torch.float64)
    torch.testing.assert_close(nine.failure_margin(x9), torch.tensor([0.05], dtype=torch.float64))
    # about 12.7 % of the 9D box is in collision (docs/concepts.md: about 12.7 % of the box)
    xs = nine.sample_states(200_000, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    frac = (nine.failure_margin(xs) <= 0).double().mean().item()
    assert 0.12 < frac < 0.135, frac
    # two pursuers on top of each other are not the evader's failure
    mv = MultiVehicle([Car(0.5, 1.0, "control"), Car(0.5, 1.0, "disturbance"), Car(0.5, 1.0, "disturbance")])
    x = torch.tensor([[-0.9, 0.0, 0.5, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0]], dtype=torch.float64)
    assert mv.failure_margin(x).item() > 0


def test_failure_margin_gradient_is_finite_when_cars_coincide():
    nine = MultiVehicle9D()
    x = torch.tensor([[0.2, 0.2, 0.2, 0.2, -0.5, 0.5, 0.0, 1.0, 2.0]], dtype=torch.float32, requires_grad=True)
    margin = nine.failure_margin(x)
    (g,) = torch.autograd.grad(margin.sum(), x)
    assert margin.item() == pytest.approx(-0.25)
    assert torch.isfinite(g).all()
    air = Air3D()
    x = torch.zeros(1, 3, requires_grad=True)
    (g,) = torch.autograd.grad(air.failure_margin(x).sum(), x)
    assert torch.isfinite(g).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("system", SYSTEMS[:3], ids=lambda s: s.name)
def test_dtype_and_device_are_preserved(system, dtype, device):
    x = system.sample_states(8, dtype=dtype, device=device)
    p = torch.randn(8, system.state_dim, dtype=dtype, device=device)
    for out in (
        system.dynamics(x),
        system.hamiltonian(x, p),
        system.optimal_control(x, p),
        system.dissipation_bounds(x),
        system.failure_margin(x),
        system.wrap(x * 10),
    ):
        assert out.dtype == dtype and out.device.type == torch.device(device).type
    # arbitrary leading batch dimensions
    assert system.hamiltonian(x.reshape(2, 4, -1), p.reshape(2, 4, -1)).shape == (2, 4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_wrap_is_half_open_interval(dtype):
    values = torch.tensor(
        [math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 1e3, -1e3, 0.0, 2 * math.pi - 1e-7], dtype=dtype
    )
    w = TORCH.wrap_angle(values)
    pi = torch.tensor(math.pi, dtype=dtype)
    assert ((w >= -pi) & (w < pi)).all(), w
    # same angle modulo 2 pi
    assert torch.allclose(torch.cos(w), torch.cos(values), atol=1e-4 if dtype == torch.float32 else 1e-10)
    assert TORCH.wrap_angle(torch.tensor([math.pi], dtype=dtype)).item() == pytest.approx(-math.pi)
    assert FLOAT.wrap_angle(math.pi) == -math.pi
    assert -math.pi <= FLOAT.wrap_angle(-1e-20) < math.pi
    assert -math.pi <= float(NUMPY.wrap_angle(np.array(-1e-20))) < math.pi


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-5, 5, allow_nan=False), min_size=15, max_size=15),
    st.lists(st.floats(-2, 2, allow_nan=False), min_size=5, max_size=5),
)
def test_backends_agree(state, inputs):
    for system in SYSTEMS:
        n = system.state_dim
        x = state[:n]
        u = inputs[: system.control_dim]
        d = inputs[: system.disturbance_dim]
        f_float = system.xdot_columns(list(x), u, d, FLOAT)
        f_numpy = NUMPY.stack(
            system.xdot_columns(
                NUMPY.unbind(np.array([x])), [np.array([v]) for v in u], [np.array([v]) for v in d], NUMPY
            )
        )
        f_torch = system.dynamics(
            torch.tensor([x], dtype=torch.float64),
            torch.tensor([u], dtype=torch.float64),
            torch.tensor([d], dtype=torch.float64) if d else None,
        )
        np.testing.assert_allclose(f_numpy[0], f_float, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(f_torch[0].numpy(), f_float, rtol=1e-12, atol=1e-12)
        # the kind's terminal margin l (the failure margin of an avoid system, else the target's)
        x_torch = TORCH.unbind(torch.tensor([x], dtype=torch.float64))
        assert float(system.terminal_margin_columns(x, FLOAT)) == pytest.approx(
            float(system.terminal_margin_columns(x_torch, TORCH)[0]), abs=1e-12
        )


def test_registry_and_config_round_trip():
    for system in SYSTEMS:
        rebuilt = system_from_config(system.config())
        assert rebuilt == system and rebuilt.config() == system.config()
    assert make_system("MultiVehicle9D") == MultiVehicle9D()
    assert Air3D(collision_radius=0.3) != Air3D()
    with pytest.raises(ValueError, match="unknown system 'air4d'"):
        make_system("air4d")


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"speed": 0.0, "max_turn_rate": 1.0}, "speed"),
        ({"speed": 1.0, "max_turn_rate": -1.0}, "max_turn_rate"),
        ({"speed": float("nan"), "max_turn_rate": 1.0}, "speed"),
        ({"speed": 1.0, "max_turn_rate": 1.0, "role": "referee"}, "role"),
    ],
)
def test_invalid_cars_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        Car(**kwargs)


def test_invalid_systems_name_the_field():
    with pytest.raises(ValueError, match="collision_radius"):
        MultiVehicle9D(collision_radius=0.0)
    with pytest.raises(ValueError, match="at least 2 cars"):
        MultiVehicle([])
    with pytest.raises(ValueError, match="role 'control'"):
        MultiVehicle([Car(1.0, 1.0, "disturbance"), Car(1.0, 1.0, "disturbance")])
    with pytest.raises(ValueError, match="pursuer_speed"):
        Air3D(pursuer_speed=-1.0)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        Air3D().hamiltonian(torch.zeros(4, 2), torch.zeros(4, 2))


@pytest.mark.parametrize("system", [MultiVehicle9D(), MultiVehicle6D()], ids=lambda s: s.name)
def test_margin_floor_bounds_the_margin_under_adversarial_and_random_turns(system):
    """No input sequence brings l below the heading-aware floor within its time: cars steering at
    each other at full rate (the worst case the bound is built on) and random bang-bang turns,
    integrated with explicit Euler; and the floor is never looser than the speed-only default."""
    n, dt, time = system.num_cars, 0.0025, 0.4
    gen = torch.Generator().manual_seed(4)
    x0 = system.sample_states(4000, generator=gen, dtype=torch.float64) * 0.6
    floor = system.margin_floor(x0, time)
    default = system.failure_margin(x0) - system.margin_rate_bound() * time
    assert (floor >= default - 1e-12).all() and (floor > default + 0.05).float().mean() > 0.3
    rates = torch.tensor(system.car_max_turn_rates, dtype=torch.float64)
    speeds = torch.tensor([c.speed for c in system.cars], dtype=torch.float64)
    for policy in ("pursue", "random"):
        x, lowest = x0.clone(), system.failure_margin(x0)
        for _ in range(round(time / dt)):
            px, py, th = x[:, 0 : 2 * n : 2], x[:, 1 : 2 * n : 2], x[:, 2 * n :]
            if policy == "pursue":  # each car turns at full rate towards the nearest other car
                dx, dy = px.unsqueeze(1) - px.unsqueeze(2), py.unsqueeze(1) - py.unsqueeze(2)
                dist = torch.hypot(dx, dy) + torch.eye(n, dtype=x.dtype) * 1e9
                k = dist.argmin(-1, keepdim=True)
                bearing = torch.atan2(dy.gather(-1, k), dx.gather(-1, k)).squeeze(-1)
                turn = torch.sign(torch.remainder(bearing - th + math.pi, 2 * math.pi) - math.pi)
            else:
                turn = torch.randint(-1, 2, th.shape, generator=gen).to(x.dtype)
            step = torch.cat([speeds * torch.cos(th), speeds * torch.sin(th)], -1)
            step = torch.stack([step[:, :n], step[:, n:]], -1).reshape(len(x), 2 * n)
            x = torch.cat([x[:, : 2 * n] + dt * step, th + dt * turn * rates], -1)
            lowest = torch.minimum(lowest, system.failure_margin(x))
        assert (lowest >= floor - 1e-9).all(), policy


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
@pytest.mark.parametrize("system", [Dubins3D("reach"), DubinsReachAvoid()], ids=lambda s: s.name)
def test_target_floor_bounds_the_target_margin_and_is_tight(system, integrator):
    """No inputs (random bang-bang turns and winds, held over Euler or RK4 steps) bring the target
    margin below the declared floor within its time; driving straight at the goal's centre with the
    wind behind comes within 10 % of it, so a floor with a rate 10 % lower fails."""
    dt, steps = 0.01, 40
    gen = torch.Generator().manual_seed(8)
    x0 = system.sample_states(3000, generator=gen, dtype=torch.float64)
    advance = make_stepper(system, dt, integrator, TORCH)
    centre = torch.tensor(getattr(system, "goal", (0.0, 0.0)), dtype=torch.float64)
    wind = torch.tensor(system.disturbance_bounds.half_width) if system.disturbance_dim else None
    for policy in ("random", "straight in"):
        x = x0.clone()
        if policy == "straight in":  # head for the goal's centre, the wind behind; no turning
            to_goal = centre - x[:, :2]
            x[:, 2] = torch.atan2(to_goal[:, 1], to_goal[:, 0])
        lowest = system.target_margin(x)
        floors = {k: system.target_floor(x, k * dt) for k in (steps // 2, steps)}
        for k in range(1, steps + 1):
            if policy == "random":
                u = torch.randint(-1, 2, (len(x), 1), generator=gen).to(x.dtype) * system.control_bounds.half_width[0]
                d = None if wind is None else (torch.rand(len(x), 2, generator=gen, dtype=x.dtype) * 2 - 1) * wind
            else:
                u = torch.zeros(len(x), 1, dtype=x.dtype)
                heading = torch.stack([torch.cos(x[:, 2]), torch.sin(x[:, 2])], -1)
                d = None if wind is None else heading.sign() * wind
            uc = system.input_columns(u, system.control_bounds, "u")
            dc = system.input_columns(d, system.disturbance_bounds, "d")
            x = TORCH.stack(advance(TORCH.unbind(x), uc, dc), like=x[:, 0])
            lowest = torch.minimum(lowest, system.target_margin(x))
            if k in floors:
                assert (lowest >= floors[k] - 1e-9).all(), (policy, k)
        if policy == "straight in":  # where the goal stays out of reach, a 10 % slower rate breaks
            rate = (system.target_floor(x0, 0.0) - system.target_floor(x0, 1.0))[0]
            far = floors[steps] > 0
            looser = floors[steps] + 0.1 * rate * steps * dt
            assert far.float().mean() > 0.3 and ((lowest < looser - 1e-9) & far).float().mean() > 0.3


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
@pytest.mark.parametrize("avoid_only", [False, True], ids=["reach-avoid", "avoid"])
def test_narrow_passage_floors_bound_its_margins_and_are_tight(avoid_only, integrator):
    """No inputs (random bang-bang throttle and steering, held over Euler or RK4 steps, speed limits
    as the stepper keeps them) bring NarrowPassage's target margin or its clearance below the floors
    it declares within their time; both cars driving straight at their goals at full throttle come
    within 10 % of the target floor's drop where the goal stays out of reach."""
    from reach.systems.deepreach_catalogue import NarrowPassage

    system = NarrowPassage(avoid_only=avoid_only)
    dt, steps = 0.01, 40
    gen = torch.Generator().manual_seed(3)
    x0 = system.sample_states(3000, generator=gen, dtype=torch.float64)
    advance = make_stepper(system, dt, integrator, TORCH)
    for policy in ("random", "straight in"):
        x = x0.clone()
        if policy == "straight in":  # each car faces its goal, wheels straight, speed in [0.001, 4]
            for o, (gx, gy) in zip((0, 5), system.goals):
                x[:, o + 2] = torch.atan2(gy - x[:, o + 1], gx - x[:, o])
                x[:, o + 3] = x[:, o + 3].clamp(0.001, 4.0)
                x[:, o + 4] = 0.0
        floors = {k: (system.target_floor(x, k * dt), system.margin_floor(x, k * dt)) for k in (steps // 2, steps)}
        lowest_clearance = system.failure_margin(x)
        lowest_target = None if avoid_only else system.target_margin(x)
        for k in range(1, steps + 1):
            if policy == "random":
                u = torch.randint(-1, 2, (len(x), 4), generator=gen).to(x.dtype)
            else:  # full throttle (a = 2), no steering (psi = 0: the centre of its box)
                u = torch.tensor([1.0, 0.0, 1.0, 0.0], dtype=x.dtype).expand(len(x), 4)
            uc = system.input_columns(u, system.control_bounds, "u")
            x = TORCH.stack(advance(TORCH.unbind(x), uc, None), like=x[:, 0])
            if not avoid_only:
                lowest_target = torch.minimum(lowest_target, system.target_margin(x))
            lowest_clearance = torch.minimum(lowest_clearance, system.failure_margin(x))
            if k in floors:
                target_floor, clearance_floor = floors[k]
                assert (lowest_clearance >= clearance_floor - 1e-9).all(), (policy, k)
                assert avoid_only == (target_floor is None)
                if target_floor is not None:
                    assert (lowest_target >= target_floor - 1e-9).all(), (policy, k)
        if policy == "straight in" and not avoid_only:
            start = system.target_floor(x0, 0.0)
            final = floors[steps][0]
            far = final > 0
            drop_floor, drop = (start - final)[far], (start - lowest_target)[far]
            assert far.float().mean() > 0.3 and (drop >= 0.9 * drop_floor).float().mean() > 0.9
