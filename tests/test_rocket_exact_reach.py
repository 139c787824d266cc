"""benchmarks/rocket_exact_reach.py: the reach rocket's exact reach set, checked against simulated
thrust (every state some simulated input lands from is in the set; a constant world-frame thrust at
the set's rim lands) and against the zone itself."""

from __future__ import annotations

import math

import pytest
import torch

from reach.systems import RocketLanding


@pytest.fixture()
def exact(monkeypatch):
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import rocket_exact_reach

    return rocket_exact_reach.exactly_reachable


def _lands(system: RocketLanding, x: torch.Tensor, world_thrust: torch.Tensor, dt: float = 0.001) -> torch.Tensor:
    """Simulate the system's own dynamics with a body-frame input that holds ``world_thrust`` (N, k, 2)
    in the world frame (a new one each ``1 / k`` of the horizon); whether the zone is met."""
    x = x.double().clone()
    landed = torch.zeros(x.shape[0], dtype=torch.bool)
    steps = round(system.horizon / dt)
    for k in range(steps + 1):
        margin = torch.maximum(x[:, 0].abs() - system.landing_half_width, x[:, 1] - system.landing_height)
        landed |= margin <= 0
        a = world_thrust[:, min(k * world_thrust.shape[1] // steps, world_thrust.shape[1] - 1)]
        c, s = torch.cos(x[:, 2]), torch.sin(x[:, 2])
        u = torch.stack([c * a[:, 0] + s * a[:, 1], -s * a[:, 0] + c * a[:, 1]], -1)  # R(th)^T a
        x = x + dt * system.dynamics(x, u)
    return landed


def test_every_landing_input_starts_inside_the_exact_set(exact):
    system = RocketLanding()
    g = torch.Generator().manual_seed(0)
    x = system.sample_states(400, generator=g, dtype=torch.float64)
    angles = torch.rand((400, 4), generator=g, dtype=torch.float64) * 2 * math.pi
    thrust = system.thrust * torch.stack([torch.cos(angles), torch.sin(angles)], -1)
    landed = _lands(system, x, thrust)
    assert int(landed.sum()) > 20  # the check has cases
    assert bool(exact(system, x)[landed].all())


def test_the_exact_sets_states_land_under_a_constant_thrust_at_its_rim(exact):
    """From each state the set holds, aim at the zone point the reachable disc first touches: a
    constant world-frame thrust of full size towards it lands."""
    system = RocketLanding()
    x = system.sample_states(2000, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    inside = exact(system, x, 400)
    x = x[inside][:200]
    t = torch.linspace(0.0, system.horizon, 401, dtype=torch.float64)[:, None]
    cx, cy = x[:, 0] + x[:, 3] * t, x[:, 1] + x[:, 4] * t - 0.5 * system.gravity * t**2
    nearest_x = cx.clamp(-system.landing_half_width, system.landing_half_width)
    nearest_y = cy.clamp(max=system.landing_height)
    gap = torch.hypot(nearest_x - cx, nearest_y - cy) - 0.5 * system.thrust * t**2
    first = (gap <= 0).double().argmax(0)  # the first time the disc meets the zone
    pick = torch.arange(len(x))
    aim = torch.stack([nearest_x[first, pick] - cx[first, pick], nearest_y[first, pick] - cy[first, pick]], -1)
    direction = aim / aim.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    assert bool(_lands(system, x, (system.thrust * direction)[:, None, :], dt=0.0005).all())


def test_the_zone_is_reachable_and_a_rocket_far_off_flying_away_is_not(exact):
    system = RocketLanding()
    x = torch.tensor([[0.0, 15.0, 0.0, 0.0, 0.0, 0.0], [150.0, 150.0, 0.0, 200.0, 200.0, 0.0]])
    assert exact(system, x).tolist() == [True, False]


@pytest.fixture()
def module(exact):
    import rocket_exact_reach

    return rocket_exact_reach


def test_the_closed_form_disc_margin_is_the_least_margin_over_the_disc(module):
    """Against the margin sampled over each disc's area (polar grid): never above it, and within the
    grid's spacing of it; centres inside, beside and above the zone, small and large discs."""
    g = torch.Generator().manual_seed(2)
    centre = torch.rand(200, 2, generator=g, dtype=torch.float64) * 200 - 100
    radius = torch.rand(200, generator=g, dtype=torch.float64) * 60
    r, a = torch.meshgrid(
        torch.linspace(0, 1, 121, dtype=torch.float64), torch.linspace(0, 2 * math.pi, 361, dtype=torch.float64),
        indexing="ij",
    )  # fmt: skip
    px = centre[:, 0, None, None] + radius[:, None, None] * r * torch.cos(a)
    py = centre[:, 1, None, None] + radius[:, None, None] * r * torch.sin(a)
    sampled = torch.maximum(px.abs() - 20, py - 20).flatten(1).amin(-1)
    closed = module.disc_box_margin(centre[:, 0].abs() - 20, centre[:, 1] - 20, radius)
    assert bool((closed <= sampled + 1e-9).all())
    spacing = radius * max(1 / 120, 2 * math.pi / 360)
    assert bool((sampled - closed <= spacing + 1e-9).all())
    assert float(closed.min()) == -20.0  # some disc holds (0, y <= 0): the margin's floor


def test_the_closed_form_value_is_the_exact_set_and_starts_at_the_margin(module):
    system = RocketLanding()
    x = system.sample_states(3000, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    vf = module.ExactRocketValue(system, 400)
    assert torch.equal(vf.value(x, 0.0), system.target_margin(x))
    claims = vf.value(x, system.horizon) <= 0
    assert torch.equal(claims, module.exactly_reachable(system, x, 400)) and 0.2 < float(claims.double().mean()) < 0.6
    v, grad = vf.value_and_gradient(x, torch.full((3000,), system.horizon, dtype=torch.float64))
    assert torch.equal(v, vf.value(x, system.horizon)) and bool(torch.isfinite(grad).all())
    assert bool((grad[:, [2, 5]] == 0).all())  # neither heading nor turn rate changes what can land
    with pytest.raises(ValueError, match=r"time-to-go t = 1.5 lies outside \[0, 1\]"):
        vf.value(x, 1.5)
    # at t = 0 the disc is a point: the gradient is the margin's, finite (the root's branch is not taken)
    assert bool(torch.isfinite(vf.gradient(x, 0.0)).all())


def test_the_closed_forms_gradient_policy_lands_from_what_it_claims(module):
    """The value's own policy (u* from its gradient, the system's, as the cards roll out) lands from
    each of 60 claimed states at a fine step: the closed form steers, not only classifies."""
    from safety.verification.rollout import rollout

    system = RocketLanding()
    x = system.sample_states(400, generator=torch.Generator().manual_seed(4))
    vf = module.ExactRocketValue(system, 200)
    claimed = x[vf.value(x, system.horizon) <= 0][:60]
    assert len(claimed) == 60
    assert not bool(rollout(vf, claimed, dt=0.0005, progress=False).failed.any())


def test_the_closest_approach_skips_non_finite_steps(module):
    from types import SimpleNamespace

    states = torch.zeros(3, 2, 6)
    states[:, 0, :2] = torch.tensor([[50.0, 60.0], [30.0, 25.0], [math.nan, math.nan]])  # 30 m, then 10 m, then NaN
    states[:, 1, :2] = torch.tensor([[0.0, 10.0], [0.0, 30.0], [0.0, 20.5]])  # inside (-10), 10 m, 0.5 m
    miss = module.closest_approach(RocketLanding(), SimpleNamespace(trajectories=states))
    assert miss.tolist() == [10.0, -10.0]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ([], "name at least one value function (a run, pretrained:NAME, or exact)"),
        (["exact", "--dt", "0"], "argument --dt: must be > 0, got 0.0"),
        (["pretrained:rocketlanding", "--time-steps", "0"], "argument --time-steps: must be >= 1, got 0"),
        (["pretrained:air3d"], "not a reach problem (rocketlanding): their values do not compare"),
    ],
)
def test_bad_arguments_stop_in_one_line_before_any_rollout(args, message):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "rocket_exact_reach.py"
    done = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1].endswith(message)
    assert "uniform states" not in done.stdout  # nothing was sampled or rolled out
