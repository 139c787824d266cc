"""DeepReach's public-release systems (reach.systems.deepreach_catalogue) against DeepReach's own
hand-written Hamiltonians, optimal controls, dynamics and boundary functions, restated here.

The references below restate DeepReach's ``dynamics/dynamics.py`` (branch ``public_release``,
commit 2c3bf67) formula by formula; the systems derive theirs from declared physics, so an
agreement checks both.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from reach.systems import (
    FLOAT,
    NUMPY,
    NarrowPassage,
    ParameterizedVertDrone2D,
    Quadrotor,
    ReachAvoidRocketLanding,
    RocketLanding,
    make_system,
)

F64 = torch.float64
TOL = {"rtol": 1e-12, "atol": 1e-9}

CASES = [
    ("narrowpassage", {}, "reach-avoid"),
    ("narrowpassage", {"avoid_only": True}, "avoid"),
    ("narrowpassage", {"avoid_fn_weight": 2.5, "horizon": 3.0}, "reach-avoid"),
    ("quadrotor", {}, "avoid"),
    ("quadrotor", {"set_mode": "reach", "collisionR": 0.3, "thrust_max": 5.0}, "reach"),
    ("parameterizedvertdrone2d", {}, "avoid"),
    ("parameterizedvertdrone2d", {"gravity": 9.81, "input_multiplier_max": 20.0, "input_magnitude_max": 2.0}, "avoid"),
    ("rocketlanding", {}, "reach"),
    ("reachavoidrocketlanding", {"horizon": 2.0}, "reach-avoid"),
]


def _batch(system, n=2000, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = system.sample_states(n, g, dtype=F64)
    p = torch.randn((n, system.state_dim), generator=g, dtype=F64) * 3.0
    return x, p


@pytest.mark.parametrize(("name", "kwargs", "kind"), CASES)
def test_constructs_rebuilds_and_registers(name, kwargs, kind):
    system = make_system(name, **kwargs)
    assert system.kind == kind
    assert type(system)(**system.parameters()) == system
    assert make_system(system.config()["name"], **system.parameters()) == system
    assert system.deepreach is not None and len(system.deepreach.state_scale) == system.state_dim
    x, p = _batch(system, 8)
    assert system.hamiltonian(x, p).shape == (8,)
    assert torch.isfinite(system.boundary_value(x)).all()


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="set_mode"):
        Quadrotor(set_mode="both")
    with pytest.raises(ValueError, match="avoid_only"):
        NarrowPassage(avoid_only="yes")
    with pytest.raises(ValueError, match="input_multiplier_max"):
        ParameterizedVertDrone2D(input_multiplier_max=0.0)


# ---------------------------------------------------------------- NarrowPassage, restated
L = 2.0


def _np_bounds(x):
    """Per car: the admissible (low, high) of acceleration and steering rate (DeepReach zeroes the
    side of a bound that would push v out of (0.001, 6.5) or phi out of +-(0.3 pi - 0.001))."""
    steer = 0.3 * math.pi - 0.001
    out = []
    for v, phi in ((x[..., 3], x[..., 4]), (x[..., 8], x[..., 9])):
        one = torch.ones_like(v)
        out.append((torch.where(v > 0.001, -4.0 * one, 0 * one), torch.where(v < 6.5, 2.0 * one, 0 * one)))
        out.append(
            (
                torch.where(phi > -steer, -3 * math.pi * one, 0 * one),
                torch.where(phi < steer, 3 * math.pi * one, 0 * one),
            )
        )
    return out  # a1, psi1, a2, psi2


def _np_dsdt(x, a):
    cols = []
    for o, c in ((0, 0), (5, 2)):
        th, v, phi = x[..., o + 2], x[..., o + 3], x[..., o + 4]
        cols += [v * torch.cos(th), v * torch.sin(th), v * torch.tan(phi) / L, a[..., c], a[..., c + 1]]
    return torch.stack(cols, dim=-1)


def _np_optimal(x, p, avoid_only):
    """DeepReach: avoid picks the high bound unless the costate is negative; reach-avoid picks the
    low bound where the costate is positive."""
    chosen = []
    for (lo, hi), i in zip(_np_bounds(x), (3, 4, 8, 9)):
        take_low = p[..., i] < 0 if avoid_only else p[..., i] > 0
        chosen.append(torch.where(take_low, lo, hi))
    return torch.stack(chosen, dim=-1)


def _np_hamiltonian(x, p, avoid_only):
    return (p * _np_dsdt(x, _np_optimal(x, p, avoid_only))).sum(-1)


def _np_states(system, n=2000, seed=1):
    """Domain samples plus states on every side of the speed and steering saturations."""
    x, p = _batch(system, n, seed)
    steer = 0.3 * math.pi - 0.001
    for k, (v, phi) in enumerate([(0.0005, steer + 0.0005), (6.8, -steer - 0.0005), (-0.5, 0.0), (3.0, 0.9)]):
        x[k::7, 3], x[k::7, 4] = v, phi
        x[k::5, 8], x[k::5, 9] = v, -phi
    return x, p


def _np_reach(x):
    d1 = torch.linalg.vector_norm(x[..., 0:2] - torch.tensor([6.0, -1.4], dtype=F64), dim=-1) - L
    d2 = torch.linalg.vector_norm(x[..., 5:7] - torch.tensor([-6.0, 1.4], dtype=F64), dim=-1) - L
    return torch.maximum(d1, d2)


def _np_avoid(x, weight):
    y1, y2 = x[..., 1], x[..., 6]
    lower = torch.minimum(y1 + 2.8 - L / 2, y2 + 2.8 - L / 2)
    upper = torch.minimum(2.8 - y1 - L / 2, 2.8 - y2 - L / 2)
    car = torch.tensor([0.0, -1.8], dtype=F64)
    stranded = torch.minimum(
        torch.linalg.vector_norm(x[..., 0:2] - car, dim=-1) - L, torch.linalg.vector_norm(x[..., 5:7] - car, dim=-1) - L
    )
    mutual = torch.linalg.vector_norm(x[..., 0:2] - x[..., 5:7], dim=-1) - L
    return weight * torch.minimum(torch.minimum(torch.minimum(lower, upper), stranded), mutual)


@pytest.mark.parametrize("avoid_only", [False, True])
def test_narrow_passage_hamiltonian_and_control_match_deepreach(avoid_only):
    system = NarrowPassage(avoid_only=avoid_only)
    x, p = _np_states(system)
    torch.testing.assert_close(system.hamiltonian(x, p), _np_hamiltonian(x, p, avoid_only), **TOL)
    u = system.optimal_control(x, p)
    assert float(u.abs().max()) <= 1.0
    torch.testing.assert_close(system.physical_controls(x, u), _np_optimal(x, p, avoid_only), **TOL)
    # the dynamics with the normalised inputs are DeepReach's with the physical ones
    g = torch.Generator().manual_seed(3)
    w = 2 * torch.rand((len(x), 4), generator=g, dtype=F64) - 1
    torch.testing.assert_close(system.dynamics(x, w), _np_dsdt(x, system.physical_controls(x, w)), **TOL)
    # every backend runs the same physics
    for k in range(5):
        xs, ps = x[k].tolist(), p[k].tolist()
        assert system.hamiltonian_columns(xs, ps, FLOAT) == pytest.approx(float(system.hamiltonian(x[k], p[k])), 1e-12)
    h_np = system.hamiltonian_columns(NUMPY.unbind(x.numpy()), NUMPY.unbind(p.numpy()), NUMPY)
    np.testing.assert_allclose(h_np, system.hamiltonian(x, p).numpy(), rtol=1e-12, atol=1e-9)


def test_narrow_passage_margins_match_deepreach():
    for weight in (1.0, 2.5):
        system = NarrowPassage(avoid_fn_weight=weight)
        x, _ = _np_states(system)
        torch.testing.assert_close(system.target_margin(x), _np_reach(x), **TOL)
        torch.testing.assert_close(system.constraint_margin(x), _np_avoid(x, weight), **TOL)
        torch.testing.assert_close(system.boundary_value(x), torch.maximum(_np_reach(x), -_np_avoid(x, weight)), **TOL)
        alone = NarrowPassage(avoid_fn_weight=weight, avoid_only=True)
        torch.testing.assert_close(alone.boundary_value(x), _np_avoid(x, weight), **TOL)
        torch.testing.assert_close(alone.failure_margin(x), _np_avoid(x, weight), **TOL)


# ---------------------------------------------------------------- Quadrotor, restated
def _quad_terms(x, p):
    """DeepReach's drift term of H and the four motors' switching functions."""
    qw, qx, qy, qz = x[..., 3], x[..., 4], x[..., 5], x[..., 6]
    vx, vy, vz, wx, wy, wz = (x[..., i] for i in range(7, 13))
    c1, c2 = 2 * (qw * qy + qx * qz), 2 * (-qw * qx + qy * qz)
    c3 = 1 - 2 * qx**2 - 2 * qy**2
    c45 = 4 * math.sqrt(2) / (3 * 0.17)
    c6 = 12 * 0.016 / (7 * 0.17**2)
    thrust = p[..., 7] * c1 + p[..., 8] * c2 + p[..., 9] * c3
    s = torch.stack(
        [
            thrust + p[..., 10] * c45 - p[..., 11] * c45 + p[..., 12] * c6,
            thrust - p[..., 10] * c45 - p[..., 11] * c45 - p[..., 12] * c6,
            thrust - p[..., 10] * c45 + p[..., 11] * c45 + p[..., 12] * c6,
            thrust + p[..., 10] * c45 + p[..., 11] * c45 - p[..., 12] * c6,
        ],
        dim=-1,
    )
    drift = (
        p[..., 0] * vx
        + p[..., 1] * vy
        + p[..., 2] * vz
        - p[..., 3] * (wx * qx + wy * qy + wz * qz) / 2
        + p[..., 4] * (wx * qw + wz * qy - wy * qz) / 2
        + p[..., 5] * (wy * qw - wz * qx + wx * qz) / 2
        + p[..., 6] * (wz * qw + wy * qx - wx * qy) / 2
        - 9.8 * p[..., 9]
        - p[..., 10] * 5 * wy * wz / 9
        + p[..., 11] * 5 * wx * wz / 9
    )
    return drift, s, (c1, c2, c3, c45, c6)


def _quad_dsdt(x, u):
    qw, qx, qy, qz = x[..., 3], x[..., 4], x[..., 5], x[..., 6]
    wx, wy, wz = x[..., 10], x[..., 11], x[..., 12]
    _, _, (c1, c2, c3, c45, c6) = _quad_terms(x, torch.zeros_like(x))
    u1, u2, u3, u4 = u.unbind(-1)
    total = u1 + u2 + u3 + u4
    return torch.stack(
        [
            x[..., 7],
            x[..., 8],
            x[..., 9],
            -(wx * qx + wy * qy + wz * qz) / 2,
            (wx * qw + wz * qy - wy * qz) / 2,
            (wy * qw - wz * qx + wx * qz) / 2,
            (wz * qw + wy * qx - wx * qy) / 2,
            c1 * total,
            c2 * total,
            -9.8 + c3 * total,
            c45 * (u1 - u2 - u3 + u4) - 5 * wy * wz / 9,
            c45 * (-u1 - u2 + u3 + u4) + 5 * wx * wz / 9,
            c6 * (u1 - u2 + u3 - u4),
        ],
        dim=-1,
    )


def test_quadrotor_avoid_matches_deepreach():
    system = Quadrotor(thrust_max=7.0)
    x, p = _batch(system, seed=4)
    drift, s, _ = _quad_terms(x, p)
    torch.testing.assert_close(system.hamiltonian(x, p), drift + 7.0 * s.abs().sum(-1), **TOL)
    torch.testing.assert_close(system.optimal_control(x, p), 7.0 * torch.sign(s), **TOL)
    u = (2 * torch.rand((len(x), 4), generator=torch.Generator().manual_seed(5), dtype=F64) - 1) * 7.0
    torch.testing.assert_close(system.dynamics(x, u), _quad_dsdt(x, u), **TOL)
    assert system.optimal_disturbance(x, p).shape == (len(x), 0)


def test_quadrotor_reach_is_the_minimising_mirror():
    """DeepReach leaves the reach Hamiltonian unwritten; ours minimises over the same box."""
    system = Quadrotor(set_mode="reach", thrust_max=7.0)
    x, p = _batch(system, seed=6)
    drift, s, _ = _quad_terms(x, p)
    torch.testing.assert_close(system.hamiltonian(x, p), drift - 7.0 * s.abs().sum(-1), **TOL)
    torch.testing.assert_close(system.optimal_control(x, p), -7.0 * torch.sign(s), **TOL)


def test_quadrotor_margins_match_deepreach():
    for mode in ("avoid", "reach"):
        system = Quadrotor(collisionR=0.4, set_mode=mode)
        x, _ = _batch(system, seed=7)
        expected = torch.linalg.vector_norm(x[..., :3], dim=-1) - 0.4
        torch.testing.assert_close(system.boundary_value(x), expected, **TOL)
        torch.testing.assert_close(system.terminal_margin(x), expected, **TOL)


# ---------------------------------------------------------------- ParameterizedVertDrone2D, restated
def test_vert_drone_matches_deepreach():
    system = ParameterizedVertDrone2D(gravity=9.81, input_multiplier_max=15.0, input_magnitude_max=1.5)
    x, p = _batch(system, seed=8)
    v, k = x[..., 0], x[..., 2]
    expected = k * (p[..., 0] * 1.5).abs() - p[..., 0] * 9.81 + p[..., 1] * v
    torch.testing.assert_close(system.hamiltonian(x, p), expected, **TOL)
    # DeepReach writes no optimal control here: the maximiser of k u p_v over |u| <= 1.5 (k >= 0)
    torch.testing.assert_close(system.optimal_control(x, p)[..., 0], 1.5 * torch.sign(k * p[..., 0]), **TOL)
    u = 3 * torch.rand((len(x), 1), generator=torch.Generator().manual_seed(9), dtype=F64) - 1.5
    dsdt = torch.stack([k * u[..., 0] - 9.81, v, torch.zeros_like(v)], dim=-1)
    torch.testing.assert_close(system.dynamics(x, u), dsdt, **TOL)
    torch.testing.assert_close(system.failure_margin(x), 1.5 - (x[..., 1] - 1.5).abs(), **TOL)


# ---------------------------------------------------------------- the rockets (a disc of thrust)
def _rocket_coefficients(x, p):
    """DeepReach's two thrust coefficients, restated: the costate seen through the rocket's heading."""
    c, s = torch.cos(x[:, 2]), torch.sin(x[:, 2])
    return p[:, 3] * c + p[:, 4] * s + 0.3 * p[:, 5], -p[:, 3] * s + p[:, 4] * c


def _rocket_hamiltonian(x, p):
    a, b = _rocket_coefficients(x, p)
    drift = p[:, 0] * x[:, 3] + p[:, 1] * x[:, 4] + p[:, 2] * x[:, 5] - 9.81 * p[:, 4]
    return drift - 250.0 * torch.sqrt(a * a + b * b)


def _rocket_thrust(x, p):
    a, b = _rocket_coefficients(x, p)
    angle = torch.atan2(b, a) + math.pi  # against the coefficients, at full thrust
    return torch.stack([250.0 * torch.cos(angle), 250.0 * torch.sin(angle)], -1)


def _rocket_target(x):
    m = torch.maximum(x[:, 0].abs() - 20.0, x[:, 1] - 20.0)
    return torch.where(m >= 0, m / 150.0, m / 10.0)


def _rocket_wall(x):
    dx = torch.maximum(-30.0 - x[:, 0], x[:, 0] + 20.0)
    dy = torch.maximum(0.0 - x[:, 1], x[:, 1] - 100.0)
    outside = torch.sqrt(dx.clamp_min(0) ** 2 + dy.clamp_min(0) ** 2)
    return torch.minimum(x[:, 1], outside + torch.maximum(dx, dy).clamp_max(0))


@pytest.mark.parametrize("system", [RocketLanding(), ReachAvoidRocketLanding()], ids=lambda s: s.name)
def test_rockets_match_deepreach_with_a_disc_of_thrust(system):
    x, p = _batch(system)
    torch.testing.assert_close(system.hamiltonian(x, p), _rocket_hamiltonian(x, p), **TOL)
    torch.testing.assert_close(system.optimal_control(x, p), _rocket_thrust(x, p), **TOL)
    torch.testing.assert_close(system.target_margin(x), _rocket_target(x), **TOL)
    if system.kind == "reach-avoid":
        torch.testing.assert_close(system.constraint_margin(x), _rocket_wall(x), **TOL)
        torch.testing.assert_close(system.boundary_value(x), torch.maximum(_rocket_target(x), -_rocket_wall(x)), **TOL)
    # H is the minimum over the disc: no thrust on a fine ring of the boundary does better
    angles = torch.linspace(0, 2 * math.pi, 721, dtype=F64)[:-1]
    ring = 250.0 * torch.stack([torch.cos(angles), torch.sin(angles)], -1)
    xs, ps = x[:50], p[:50]
    xdot = system.dynamics(xs.repeat_interleave(len(ring), 0), ring.repeat(50, 1)).reshape(50, len(ring), 6)
    brute = (ps.unsqueeze(1) * xdot).sum(-1).min(-1).values
    assert (system.hamiltonian(xs, ps) <= brute + 1e-9).all()
    assert (brute - system.hamiltonian(xs, ps)).max() < 250.0 * 3.0 * 20 * (1 - math.cos(math.pi / 720))
    # every backend derives the same H and thrust
    for k in range(3):
        xs, ps = x[k].tolist(), p[k].tolist()
        assert system.hamiltonian_columns(xs, ps, FLOAT) == pytest.approx(float(system.hamiltonian(x[k], p[k])), 1e-12)
    h_np = system.hamiltonian_columns(NUMPY.unbind(x.numpy()), NUMPY.unbind(p.numpy()), NUMPY)
    np.testing.assert_allclose(h_np, system.hamiltonian(x, p).numpy(), rtol=1e-12, atol=1e-9)


def test_zero_costate_gives_the_disc_centre_and_a_finite_gradient():
    """Where the thrust coefficients vanish the optimal thrust is the centre (no NaN from 0/0), and
    autograd through H (training differentiates the residual) gives finite gradients there."""
    system = RocketLanding()
    x = system.sample_states(4, torch.Generator().manual_seed(0), dtype=F64)
    p = torch.zeros(4, 6, dtype=F64)
    p[:, 0] = 1.0  # no component on the velocities or the rate: coefficients 0
    assert torch.equal(system.optimal_control(x, p), torch.zeros(4, 2, dtype=F64))
    p.requires_grad_(True)
    (grad,) = torch.autograd.grad(system.hamiltonian(x, p).sum(), p)
    assert torch.isfinite(grad).all()


# ---------------------------------------------------------------- importing DeepReach's public release
def _deepreach_forward(state_dict, inputs, layout):
    """DeepReach's sine MLP, restated: sin(30 (W h + b)) per activated layer, then a linear output."""
    h = inputs
    for i, letter in enumerate(layout[:-1]):
        z = h @ state_dict[f"net.net.{i}.0.weight"].T + state_dict[f"net.net.{i}.0.bias"]
        h = torch.sin(30.0 * z) if letter == "s" else torch.relu(z)
    k = len(layout) - 1
    return (h @ state_dict[f"net.net.{k}.0.weight"].T + state_dict[f"net.net.{k}.0.bias"]).squeeze(-1)


@pytest.mark.parametrize("system", [RocketLanding(), ReachAvoidRocketLanding(), NarrowPassage()], ids=lambda s: s.name)
def test_a_public_release_checkpoint_imports_as_deepreach_evaluates_it(system, tmp_path):
    """A state dict shaped as DeepReach's public release trains it (``diff_model``; RocketLanding's one
    extra zero input) loads, and its values are DeepReach's: the raw output scaled by
    ``value_var / value_normto`` plus the boundary function, on the normalised input ``(t, x, [0])``."""
    from training.deepreach import load_deepreach

    layout, width = "ssl", 16
    n, extra = system.state_dim, system.deepreach.extra_inputs
    g = torch.Generator().manual_seed(0)
    sizes = [1 + n + extra, width, width, 1]
    state = {}
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        bound = 1 / a if i == 0 else math.sqrt(6 / a) / 30  # SIREN's initialisation, DeepReach's
        state[f"net.net.{i}.0.weight"] = (torch.rand(b, a, generator=g) * 2 - 1) * bound
        state[f"net.net.{i}.0.bias"] = (torch.rand(b, generator=g) * 2 - 1) * bound
    path = tmp_path / "model_final.pth"
    torch.save(state, path)
    net = load_deepreach(path, system, layout, check_boundary=False)
    assert net.parameterisation == "diff"
    x = system.sample_states(256, g, dtype=torch.float32)
    t = torch.rand(256, generator=g)
    n_ = system.deepreach
    inputs = torch.cat(
        [t[:, None], (x - torch.tensor(n_.state_offset)) / torch.tensor(n_.state_scale), torch.zeros(256, extra)], -1
    )
    expected = _deepreach_forward(state, inputs, layout) * n_.value_scale + system.boundary_value(x)
    with torch.no_grad():
        torch.testing.assert_close(net(x, t), expected, rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match=r"model must be 'vanilla' or 'diff'"):
        load_deepreach(path, system, layout, check_boundary=False, model="exact")
    # an untrained network is far from the boundary condition: refused unless asked not to check
    with pytest.raises(ValueError, match="away from the boundary value"):
        load_deepreach(path, system, layout)
