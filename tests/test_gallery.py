"""The gallery's equations are the systems' physics: printed dynamics and margins, evaluated, equal
what envs, solvers and training compute; every built-in system has its section."""

from __future__ import annotations

import numpy as np
import pytest
import sympy
import torch

from reach.systems import make_system
from reach.systems.symbolic import _symbol, equations, tidy
from studies.gallery import GALLERY, MISSING, system_section

MARGINS = {"failure": "failure_margin", "target": "target_margin", "constraint": "constraint_margin"}


#: the 15D fleet is the 12D one's class with one more car (7 s of lambdify): left to the docs build
@pytest.mark.parametrize("name", [n for n, _ in GALLERY if n != "multivehicle15d"])
def test_printed_equations_evaluate_to_the_systems_dynamics_and_margins(name):
    system = make_system(name)
    eq = equations(system, display=False)  # exact floats; display only rounds them (tested below)
    gen = torch.Generator().manual_seed(0)
    x = system.sample_states(64, generator=gen, dtype=torch.float64)
    u = torch.rand(64, system.control_dim, generator=gen, dtype=torch.float64) * 2 - 1
    d = torch.rand(64, system.disturbance_dim, generator=gen, dtype=torch.float64) * 2 - 1
    symbols = (*eq.states, *eq.controls, *eq.disturbances)
    columns = [*x.T.numpy(), *u.T.numpy(), *d.T.numpy()]
    f = np.stack([np.broadcast_to(sympy.lambdify(symbols, e, "numpy")(*columns), (64,)) for e in eq.dynamics], -1)
    expected = system.dynamics(x, u, d if system.disturbance_dim else None).numpy()
    np.testing.assert_allclose(f, expected, rtol=1e-12, atol=1e-12)
    assert eq.margins and set(eq.margins) <= set(MARGINS)
    for key, expr in eq.margins.items():
        value = np.broadcast_to(sympy.lambdify(eq.states, expr, "numpy")(*x.T.numpy()), (64,))
        np.testing.assert_allclose(value, getattr(system, MARGINS[key])(x).numpy(), rtol=1e-12, atol=1e-12)


def test_displayed_equations_round_only_the_numbers():
    system = make_system("quadrotor")
    exact, shown = equations(system, display=False), equations(system)
    x = system.sample_states(16, generator=torch.Generator().manual_seed(1), dtype=torch.float64).T.numpy()
    u = np.random.default_rng(1).uniform(-1, 1, (system.control_dim, 16))
    symbols = (*exact.states, *exact.controls)
    for a, b in zip(exact.dynamics, shown.dynamics):
        va = np.broadcast_to(sympy.lambdify(symbols, a, "numpy")(*x, *u), (16,))
        vb = np.broadcast_to(sympy.lambdify(symbols, b, "numpy")(*x, *u), (16,))
        np.testing.assert_allclose(vb, va, rtol=1e-4, atol=1e-4)  # six significant digits per coefficient


def test_numbers_and_names_read_as_in_the_papers():
    assert str(tidy(sympy.Float(1.0) * sympy.Symbol("u"))) == "u"
    assert tidy(sympy.Float(3 * np.pi)) == 3 * sympy.pi
    assert str(tidy(sympy.Float(0.941477796076938))) == "0.941478"
    assert sympy.latex(_symbol("th3")) == r"\theta_{3}" and sympy.latex(_symbol("px")) == "p_{x}"
    assert sympy.latex(_symbol("wy")) == r"\omega_{y}" and sympy.latex(_symbol("x")) == "x"


def test_a_section_per_system_with_its_spaces_envs_and_model(tmp_path):
    (tmp_path / "gallery").mkdir()
    (tmp_path / "gallery" / "multivehicle9d.png").write_bytes(b"")
    nine = system_section("multivehicle9d", "DeepReach", tmp_path)
    assert nine.startswith("## MultiVehicle9D (`multivehicle9d`)") and "An **avoid** problem in 9D" in nine
    assert "`MultiVehicle9D-v0`" in nine and "PettingZoo agents: `car_1` (inputs [0])" in nine
    assert "`pretrained:multivehicle9d`" in nine and "(gallery/multivehicle9d.png)" in nine
    passage = system_section("narrowpassage", "DeepReach", tmp_path)
    assert "A **reach-avoid** problem in 10D" in passage and "constraint margin g" in passage
    assert "`pretrained:narrowpassage`" in passage and "gallery/narrowpassage.png" not in passage
    assert "`car_2` (inputs [2, 3])" in passage
    assert {n for n, _ in GALLERY} >= {"dubins3d", "narrowpassage", "quadrotor", "multivehicle12d", "multivehicle15d"}
    assert any("Dubins4D" in what for what, _ in MISSING)
    rocket = system_section("rocketlanding", "DeepReach", tmp_path)
    assert "control inputs (2): the disc |u - (0, 0)| <= 250" in rocket and "`RocketLanding-v0`" in rocket
    assert "`pretrained:rocketlanding`" in rocket and "false reachable %" in rocket  # a reach model's wrong claim
