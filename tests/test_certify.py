"""Formal certification by branch and bound (safety.certify): what it proves holds at every sample.

A small sine network on Air3D (``V`` close to ``l``, so the set is close to ``{l >= c}``, which the
evader can keep only in places) gives a mix of proven, refuted and unknown boxes in seconds. Every
proven box is then checked by sampling: each sampled state of the set has ``l > 0``, and the box's
backup input keeps it in the set under sampled disturbances; every counterexample is re-evaluated.
"""

from __future__ import annotations

import math

import pytest
import torch

from reach.integrators import make_stepper
from reach.systems import Air3D
from reach.systems.arrays import TORCH
from safety.certify import OUTSIDE, PROVEN, REFUTED, CertifySettings, certify
from training.network import Encoding, ValueNetwork


@pytest.fixture(scope="module")
def network() -> ValueNetwork:
    torch.manual_seed(0)
    system = Air3D()
    encoding = Encoding.for_system(system, sincos=True, value_scale=0.02, sincos_radius=1 / math.pi)
    return ValueNetwork(system, "ssl", width=16, w0=3.0, encoding=encoding)


SETTINGS = CertifySettings(level=0.3, time_to_go=1.0, dt=0.05, initial_splits=6, min_relative_width=1 / 24, batch=256)


@pytest.fixture(scope="module")
def result(network):
    return certify(network, SETTINGS)


def test_the_verifier_finishes_with_proven_and_undecided_boxes(result):
    shares = result.volume_shares()
    assert result.finished and not result.certified
    assert shares["proven"] > 0.05 and shares["outside"] > 0.05
    assert abs(sum(shares.values()) - 1.0) < 1e-9
    # the boxes tile the state box: their volumes add up to it
    domain = Air3D().domain_tensor(torch.float64, "cpu")
    assert float((result.hi - result.lo).prod(-1).sum()) == pytest.approx(float((domain[:, 1] - domain[:, 0]).prod()))


def test_every_proven_box_holds_at_sampled_states_and_disturbances(network, result):
    net = network.double()
    system = net.system
    step = make_stepper(system, SETTINGS.dt, SETTINGS.integrator, TORCH)
    g = torch.Generator().manual_seed(1)
    proven = (result.status == PROVEN).nonzero().squeeze(-1)
    lo, hi = result.lo[proven], result.hi[proven]
    per_box = 16
    x = lo.repeat_interleave(per_box, 0) + (hi - lo).repeat_interleave(per_box, 0) * torch.rand(
        (len(proven) * per_box, 3), generator=g, dtype=torch.float64
    )
    u = result.candidates[result.backup[proven]].repeat_interleave(per_box, 0)
    d = -3.0 + 6.0 * torch.rand((len(x), 1), generator=g, dtype=torch.float64)
    t = torch.full((len(x),), SETTINGS.time_to_go, dtype=torch.float64)
    with torch.no_grad():
        in_set = net(x, t) >= SETTINGS.level
        assert bool((system.failure_margin(x)[in_set] > 0).all())
        nxt = TORCH.stack(step(TORCH.unbind(x), TORCH.unbind(u), TORCH.unbind(d)))
        assert bool((net(nxt, t)[in_set] >= SETTINGS.level).all())
    outside = (result.status == OUTSIDE).nonzero().squeeze(-1)
    x_out = result.lo[outside] + (result.hi[outside] - result.lo[outside]) * 0.5
    with torch.no_grad():
        assert bool((net(x_out, torch.full((len(x_out),), 1.0, dtype=torch.float64)) < SETTINGS.level).all())


def test_counterexamples_are_real(network, result):
    assert (result.status == REFUTED).any() and result.counterexamples
    net = network.double()
    for found in result.counterexamples[:20]:
        x = torch.tensor([found["state"]], dtype=torch.float64)
        with torch.no_grad():
            assert float(net(x, torch.tensor([1.0], dtype=torch.float64))) >= SETTINGS.level
        if found["reason"] == "l <= 0":
            assert float(net.system.failure_margin(x)) <= 0


def test_an_unfinished_run_is_never_certified(network):
    result = certify(network, CertifySettings(level=-100.0, time_to_go=1.0, dt=0.05, max_boxes=1, batch=8))
    assert not result.finished and not result.certified
    assert result.volume_shares()["unknown"] > 0.9


@pytest.mark.parametrize(
    ("options", "named"),
    [
        ({"level": float("nan")}, "level"),
        ({"dt": 0.0}, "dt"),
        ({"integrator": "midpoint"}, "integrator"),
        ({"batch": 0}, "batch"),
        ({"min_relative_width": 2.0}, "min_relative_width"),
        ({"max_seconds": -1.0}, "max_seconds"),
    ],
)
def test_bad_settings_are_refused_naming_them(options, named):
    base = {"level": 0.1, "time_to_go": 1.0, "dt": 0.05}
    with pytest.raises(ValueError, match=named):
        CertifySettings(**(base | options))


def test_a_time_to_go_beyond_the_horizon_is_refused(network):
    with pytest.raises(ValueError, match="beyond the value function's horizon"):
        certify(network, CertifySettings(level=0.1, time_to_go=5.0, dt=0.05))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_the_verifier_runs_on_a_gpu_and_agrees_with_the_cpu(network, result):
    on_gpu = certify(network.float(), SETTINGS, device="cuda")
    assert on_gpu.finished and on_gpu.lo.device.type == "cpu"
    cpu, gpu = result.volume_shares(), on_gpu.volume_shares()
    assert all(abs(cpu[k] - gpu[k]) < 0.02 for k in cpu), (cpu, gpu)
