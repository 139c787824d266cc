"""Formal certification by branch and bound (safety.formal.verifier): what it proves holds at every sample.

A small sine network on Air3D (``V`` close to ``l``, so the set is close to ``{l >= c}``, which the
evader can keep only in places) gives a mix of proven, refuted and unknown boxes in seconds. Every
proven box is then checked by sampling: each sampled state of the set has ``l > 0``, and the box's
backup input keeps it in the set under sampled disturbances; every counterexample is re-evaluated.
"""

from __future__ import annotations

import copy
import json
import math
import os

import numpy as np
import pytest
import torch

from reach.integrators import make_stepper
from reach.systems import Air3D, ControlAffineSystem
from reach.systems.arrays import TORCH
from reach.systems.box import Box
from safety.formal.certificate import save_certificate
from safety.formal.checker import check_certificate
from safety.formal.closure import certified_set
from safety.formal.settings import OUTSIDE, PROVEN, REFUTED, UNKNOWN, CertifySettings
from safety.formal.verifier import certify
from training.encoding import Encoding
from training.network import ValueNetwork


@pytest.fixture(scope="module")
def network() -> ValueNetwork:
    torch.manual_seed(0)
    system = Air3D()
    encoding = Encoding.for_system(system, sincos=True, value_scale=0.02, sincos_radius=1 / math.pi)
    return ValueNetwork(system, "ssl", width=16, w0=3.0, encoding=encoding)


SETTINGS = CertifySettings(level=0.3, time_to_go=1.0, dt=0.05, initial_splits=6, min_relative_width=1 / 12, batch=256)


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
        ({"escape_margin": float("nan")}, "escape_margin"),
        ({"band_min_relative_width": 2.0}, "band_min_relative_width"),
        ({"closure_refinements": -1}, "closure_refinements"),
        ({"closure_refinements": True}, "closure_refinements"),
        ({"closure_refine_reach": 0}, "closure_refine_reach"),
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


class Torus(ControlAffineSystem):
    """A user system: a point on a torus, moved by its input and pushed by a weaker disturbance, that
    must keep out of the unit disc. ``{l >= c}`` is invariant (push away from the disc), and the
    torus has no domain edge to leave by."""

    name = "torus-avoid"
    state_names = ("px", "py")
    periodic = (True, True)

    def __init__(self, horizon: float = 1.0) -> None:
        self.horizon = horizon
        self.domain = ((-math.pi, math.pi), (-math.pi, math.pi))
        self.control_bounds = Box.symmetric([1.0, 1.0])
        self.disturbance_bounds = Box.symmetric([0.3, 0.3])

    def parameters(self) -> dict:
        return {"horizon": self.horizon}

    def drift(self, x, xp):
        return [0.0 * x[0], 0.0 * x[1]]

    def control_matrix(self, x, xp):
        return {(0, 0): 1.0, (1, 1): 1.0}

    def disturbance_matrix(self, x, xp):
        return {(0, 0): 1.0, (1, 1): 1.0}

    def failure_margin_columns(self, x, xp):
        return xp.sqrt(x[0] ** 2 + x[1] ** 2) - 1.0


TORUS = CertifySettings(level=0.3, time_to_go=1.0, dt=0.05, initial_splits=8, min_relative_width=1 / 64, batch=512)


@pytest.fixture(scope="module")
def torus_network() -> ValueNetwork:
    torch.manual_seed(0)
    system = Torus()
    encoding = Encoding.for_system(system, sincos=True, value_scale=0.02, sincos_radius=1 / math.pi)
    return ValueNetwork(system, "ssl", width=16, w0=3.0, encoding=encoding)


@pytest.fixture(scope="module")
def torus_result(torus_network):
    return certify(torus_network, TORUS)


@pytest.fixture(scope="module")
def torus_certificate(torus_network, torus_result):
    return certified_set(torus_network, torus_result)


def test_a_box_about_to_drop_out_takes_another_input_that_keeps_it(torus_network, torus_result, tmp_path):
    """Holes punched in the proven boxes (5 % marked unknown) make some boxes' first inputs lead into
    them; the closure then gives such a box another candidate input that proves (b) and avoids every
    dropped box (15 boxes switched when this was written), and the certificate still checks."""
    holes = (torus_result.status == PROVEN) & (
        torch.rand(len(torus_result.status), generator=torch.Generator().manual_seed(0)) < 0.05
    )
    punched = copy.copy(torus_result)
    punched.status = torch.where(holes, torch.tensor(UNKNOWN), torus_result.status)
    certificate = certified_set(torus_network, punched)
    first = {tuple(lo.tolist()): u for lo, u in zip(torus_result.lo, torus_result.candidates[torus_result.backup])}
    switched = sum(
        not torch.equal(first[tuple(lo.tolist())], u) for lo, u in zip(certificate.kept.lo, certificate.inputs)
    )
    assert switched > 0 and len(certificate.kept.lo) > 0
    check_certificate(save_certificate(tmp_path / "punched.npz", certificate), torus_network)


@pytest.mark.parametrize("chunk", [65536, 7], ids=["one-chunk", "chunks-of-7"])
def test_the_certified_set_is_closed_and_its_file_checks(
    torus_network, torus_certificate, tmp_path, chunk, monkeypatch
):
    """The certified set, the union of the kept boxes, is closed (checked at samples: 89 % of the
    torus when this was written, every box but those meeting the disc), its file re-verifies from
    the file alone, and a changed model, level or box, or junk, is refused naming why; the same when
    the checker bounds the network a few boxes at a time."""
    monkeypatch.setattr("safety.formal.checker.CHECK_CHUNK", chunk)
    certificate = torus_certificate
    domain = Torus().domain_tensor(torch.float64, "cpu")
    assert certificate.kept_volume_share(domain) > 0.5
    path = save_certificate(tmp_path / "torus.npz", certificate)
    checked = check_certificate(path, torus_network)
    assert torch.equal(checked.kept.lo, certificate.kept.lo) and checked.resolution == certificate.resolution
    # every state of a kept box (whatever V says) is safe and steps, under its box's input and any
    # disturbance, to a state that is again in a kept box
    net = copy.deepcopy(torus_network).double()
    step = make_stepper(net.system, TORUS.dt, TORUS.integrator, TORCH)
    g = torch.Generator().manual_seed(2)
    lo, hi = certificate.kept.lo.repeat(8, 1), certificate.kept.hi.repeat(8, 1)
    x = lo + (hi - lo) * torch.rand(lo.shape, generator=g, dtype=torch.float64)
    d = -0.3 + 0.6 * torch.rand(x.shape, generator=g, dtype=torch.float64)
    u = certificate.inputs.repeat(8, 1)
    t = torch.full((len(x),), TORUS.time_to_go, dtype=torch.float64)
    with torch.no_grad():
        assert bool((net.system.failure_margin(x) > 0).all())
        nxt = net.system.wrap(TORCH.stack(step(TORCH.unbind(x), TORCH.unbind(u), TORCH.unbind(d))))
        kept_lo, kept_hi = certificate.kept.lo, certificate.kept.hi
        in_kept = ((nxt[:, None, :] >= kept_lo) & (nxt[:, None, :] <= kept_hi)).all(-1).any(-1)
        below = net(x, t) < TORUS.level
    assert bool(in_kept.all())
    assert bool(below.any())  # the set reaches beyond S_c: boxes the network calls outside are kept

    edited = copy.deepcopy(torus_network)
    with torch.no_grad():
        edited.output.bias += 1e-3
    with pytest.raises(ValueError, match="a changed model needs a new certificate"):
        check_certificate(path, edited)
    with np.load(path) as data:
        arrays = dict(data)
    grown = dict(arrays, kept_hi=arrays["kept_hi"] + 0.5 * (arrays["kept_hi"] - arrays["kept_lo"]))
    np.savez(tmp_path / "grown.npz", **grown)
    with pytest.raises(ValueError, match=r"not on the certificate.s cell grid|not a box inside the domain"):
        check_certificate(tmp_path / "grown.npz", torus_network)
    header = json.loads(str(arrays["header"]))
    header["settings"]["level"] = TORUS.level - 0.5  # the outside boxes no longer hold only V < c
    np.savez(tmp_path / "lower.npz", **dict(arrays, header=np.array(json.dumps(header))))
    with pytest.raises(ValueError, match="outside box"):
        check_certificate(tmp_path / "lower.npz", torus_network)
    swapped = dict(arrays, inputs=-arrays["inputs"])  # every backup input reversed: toward the disc
    np.savez(tmp_path / "swapped.npz", **swapped)
    with pytest.raises(ValueError, match="next states"):
        check_certificate(tmp_path / "swapped.npz", torus_network)
    (tmp_path / "junk.npz").write_bytes(b"not a certificate")
    with pytest.raises(ValueError, match="not a reach certificate"):
        check_certificate(tmp_path / "junk.npz", torus_network)
    with pytest.raises(ValueError, match=r"ends in \.npz"):
        save_certificate(tmp_path / "torus.json", certificate)


def test_boxes_cut_finer_before_the_closure_keep_at_least_as_much(torus_network, torus_result, tmp_path):
    """``closure_relative_width`` cuts the cover's boxes down to 1/64 before the closure, each part
    with its own input: every part of a box kept before can keep its input, so the set can only grow
    (from 0.891 to 0.910 of the torus when this was written), the parts tile what the boxes did, and the file checks."""
    from dataclasses import replace

    from safety.formal.closure import _refined

    domain = Torus().domain_tensor(torch.float64, "cpu")
    fine = replace(torus_result, settings=replace(TORUS, closure_relative_width=1 / 64))
    parts = _refined(fine, domain)
    span = domain[:, 1] - domain[:, 0]
    widths = (parts.hi - parts.lo) / span
    assert float(widths.max()) <= 1 / 64 + 1e-12 and len(parts.lo) > len(torus_result.lo)
    assert float(widths.prod(-1).sum()) == pytest.approx(1.0, abs=1e-12)
    coarse = certified_set(torus_network, torus_result)
    refined = certified_set(torus_network, fine)
    assert refined.kept_volume_share(domain) >= coarse.kept_volume_share(domain)
    assert len(refined.kept.lo) > len(coarse.kept.lo)
    check_certificate(save_certificate(tmp_path / "fine.npz", refined), torus_network)
    with pytest.raises(ValueError, match="closure_relative_width"):
        CertifySettings(level=0.3, time_to_go=1.0, dt=0.05, closure_relative_width=0.0)


def test_refinements_at_the_sets_edge_keep_more_and_the_file_checks(torus_network, tmp_path):
    """A coarse cover (1/8 of the span) keeps only the boxes clear of the disc. Each refinement cuts
    the boxes not kept near the kept ones (those meeting the disc) into quarters and closes again:
    the boxes kept before stay with their inputs, the set grows (0.81, 0.88, 0.90 of the torus when
    this was written), its finest boxes halve, and the file checks. A reach of one box keeps no more
    than one of eight (here the same)."""
    from dataclasses import replace

    domain = Torus().domain_tensor(torch.float64, "cpu")
    coarse = replace(TORUS, min_relative_width=1 / 8, initial_splits=8)
    result = certify(torus_network, coarse)
    shares, previous = [], None
    for refinements in (0, 1, 2):
        settings = replace(coarse, closure_refinements=refinements)
        certificate = certified_set(torus_network, replace(result, settings=settings))
        shares.append(certificate.kept_volume_share(domain))
        widths = (certificate.kept.hi - certificate.kept.lo) / (domain[:, 1] - domain[:, 0])
        assert float(widths.min()) == pytest.approx(1 / 8 / 2**refinements)
        if previous is not None:  # every box kept before is kept again, whole, with its input
            before = {tuple(lo.tolist()) + tuple(u.tolist()) for lo, u in zip(previous.kept.lo, previous.inputs)}
            now = {tuple(lo.tolist()) + tuple(u.tolist()) for lo, u in zip(certificate.kept.lo, certificate.inputs)}
            assert before <= now
        previous = certificate
    assert shares[0] < shares[1] < shares[2], shares
    check_certificate(save_certificate(tmp_path / "refined.npz", previous), torus_network)
    near = certified_set(
        torus_network, replace(result, settings=replace(coarse, closure_refinements=2, closure_refine_reach=1))
    )
    assert shares[0] < near.kept_volume_share(domain) <= shares[2]


def test_a_piece_on_a_box_face_needs_only_the_cell_on_its_side():
    """The closure's cells come from the boxes' own corners: a next-state piece that ends exactly on a
    face (a face the step leaves in place) needs only the cell on its side, one that pokes an ulp
    beyond needs the next cell too, and boxes whose corners disagree on an edge are refused."""
    from safety.formal.cover import CellGrid

    domain = torch.tensor([[-math.pi, math.pi]], dtype=torch.float64)
    third = torch.tensor([[-math.pi / 2]], dtype=torch.float64)  # an edge whose float is not (k / R) exact
    lo = torch.tensor([[-math.pi], [-math.pi / 2], [0.0], [math.pi / 2]], dtype=torch.float64)
    hi = torch.tensor([[-math.pi / 2], [0.0], [math.pi / 2], [math.pi]], dtype=torch.float64)
    grid = CellGrid(domain, 4, lo, hi)
    a, b = grid.cells(third - 0.1, third, exact=False)
    assert (int(a), int(b)) == (0, 1)
    a, b = grid.cells(third - 0.1, torch.nextafter(third, torch.tensor(math.inf, dtype=torch.float64)), exact=False)
    assert (int(a), int(b)) == (0, 2)
    a, b = grid.cells(third, third + 0.1, exact=False)
    assert (int(a), int(b)) == (1, 2)
    bent = hi.clone()
    bent[0, 0] = torch.nextafter(bent[0, 0], torch.tensor(0.0, dtype=torch.float64))
    with pytest.raises(ValueError, match="corners on one cell edge differ"):
        CellGrid(domain, 4, lo, bent)


def test_the_command_line_certifies_and_checks_in_one_line_errors(network, tmp_path, capsys):
    from reach_cli import main
    from training import save_checkpoint

    source = tmp_path / "air3d.pt"
    save_checkpoint(source, network.float())
    out = tmp_path / "cert.npz"
    args = ["certify", str(source), "--level", "0.3", "--dt", "0.05", "--initial-splits", "4", "--min-width", "0.125"]
    # a quick closure: the network's own box, cells of its finest boxes, no refinements (Air3D's
    # certification defaults close over a box four times wider, refined three times)
    args += ["--closure-scale", "1", "--closure-width", "0.125", "--closure-refinements", "0"]
    assert main([*args, "--out", str(out)]) in (0, 3)
    assert "wrote" in capsys.readouterr().out and out.exists()
    assert main(["certify", str(source), "--check", str(out)]) == 0
    assert "holds for" in capsys.readouterr().out
    progress = tmp_path / "progress.npz"
    assert main([*args, "--max-boxes", "16", "--resume", str(progress), "--out", str(out)]) in (0, 3)
    assert f"stopped (continue with --resume {progress})" in capsys.readouterr().out
    assert main([*args, "--resume", str(progress), "--out", str(out)]) in (0, 3)
    assert "finished after" in capsys.readouterr().out
    other = tmp_path / "other.pt"
    save_checkpoint(other, ValueNetwork(Air3D(), "ssl", width=16, w0=3.0))
    for bad in (
        ["certify", str(other), "--check", str(out)],
        ["certify", str(source), "--level", "0.3"],
        ["certify", str(source), "--level", "0.3", "--out", str(tmp_path / "c.json")],
        ["certify", str(source), "--check", str(out), "--level", "0.1"],
        ["certify", str(source), "--level", "nan", "--out", str(out)],
        [*args[:3], "0.2", *args[4:], "--resume", str(progress), "--out", str(out)],  # another level
        ["certify", str(source), "--check", str(out), "--resume", str(progress)],
    ):
        try:
            code = main(bad)
        except SystemExit as exit_:  # argparse's own refusal of a bad value
            code = exit_.code
        assert code == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "Traceback" not in err, err


def test_the_certified_filter_keeps_every_trajectory_safe(torus_network, torus_certificate):
    """From 64 states of the certified set, 100 steps of random nominal inputs (some outside the control
    box) and random disturbances, through the filter: every state stays certified and outside the
    disc; inputs pushing into the disc are replaced, and a non-finite state is refused."""
    from safety.formal.certified_filter import CertifiedFilter

    filt = CertifiedFilter(torus_certificate, torus_network)
    system = Torus()
    step = make_stepper(system, TORUS.dt, TORUS.integrator, TORCH)
    g = torch.Generator().manual_seed(3)
    x = system.sample_states(400, generator=g, dtype=torch.float64)
    _, info = filt(x, torch.zeros(len(x), 2, dtype=torch.float64))
    x = x[info.certified][:64]
    assert len(x) == 64
    interventions = 0
    for _ in range(100):
        nominal = -1.5 + 3.0 * torch.rand((len(x), 2), generator=g, dtype=torch.float64)
        applied, info = filt(x, nominal)
        assert bool(info.certified.all())
        interventions += int(info.intervened.sum())
        d = -0.3 + 0.6 * torch.rand((len(x), 2), generator=g, dtype=torch.float64)
        x = system.wrap(TORCH.stack(step(TORCH.unbind(x), TORCH.unbind(applied), TORCH.unbind(d))))
        assert bool((system.failure_margin(x) > 0).all())
    assert interventions > 0
    # from the kept state nearest the disc (just inside its box), full speed straight at the disc
    lo, hi = torus_certificate.kept.lo, torus_certificate.kept.hi
    near = (lo + hi) / 2 + 0.98 * (torch.zeros(2, dtype=torch.float64).clamp(lo, hi) - (lo + hi) / 2)
    nearest = near[system.failure_margin(near).argmin()][None]
    toward = -nearest / nearest.norm(dim=-1, keepdim=True)
    applied, info = filt(nearest, toward)
    assert bool(info.certified[0]) and bool(info.intervened[0]) and not torch.equal(applied, toward)
    with pytest.raises(ValueError, match="not finite"):
        filt(torch.tensor([[float("nan"), 0.0]]), torch.zeros(1, 2))


def test_the_wrappers_take_a_certificate_and_refuse_one_the_env_breaks(torus_network, torus_certificate):
    """``SafetyFilterWrapper(env, vf, certificate=...)`` filters with the certificate: an episode from a
    certified state, its nominal actions heading into the disc and a random disturbance, stays
    certified and out of the disc; another dt, process noise, filter settings beside it, or another
    model are refused."""
    from reach_envs import make_env, make_vector_env
    from safety import SafetyFilterWrapper
    from safety.filters.wrappers import SafetyFilterVectorWrapper
    from safety.formal.certified_filter import CertifiedFilter
    from training.network import NeuralValueFunction

    vf = NeuralValueFunction(torus_network)
    scene = {"dt": TORUS.dt, "integrator": TORUS.integrator, "disturbance": "random", "horizon": 5.0}
    filt = CertifiedFilter(torus_certificate, torus_network, verify=False)
    x = Torus().sample_states(400, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    start = x[filt(x, torch.zeros(len(x), 2, dtype=torch.float64))[1].certified][0].numpy()
    env = SafetyFilterWrapper(make_env(Torus(), **scene), vf, certificate=torus_certificate)
    env.reset(seed=1, options={"state": start})
    rng = np.random.default_rng(0)
    intervened = 0
    for _ in range(60):
        towards_disc = -env.unwrapped.state / np.linalg.norm(env.unwrapped.state)  # a nominal that would fail
        action = np.clip(towards_disc + rng.uniform(-0.3, 0.3, 2), -1.0, 1.0).astype(np.float32)
        _, _, terminated, _, info = env.step(action)
        assert info["filter_certified"] and not terminated
        assert float(Torus().failure_margin(torch.as_tensor(env.unwrapped.state)[None])[0]) > 0
        intervened += info["filter_intervened"]
    assert intervened > 0
    vector = SafetyFilterVectorWrapper(make_vector_env(Torus(), 3, **scene), vf, certificate=torus_certificate)
    vector.reset(seed=2)
    _, _, _, _, infos = vector.step(np.zeros((3, 2), dtype=np.float32))
    assert infos["filter_certified"].shape == (3,)
    with pytest.raises(ValueError, match=r"dt 0\.05 .*dt 0\.02"):
        SafetyFilterWrapper(make_env(Torus(), **{**scene, "dt": 0.02}), vf, certificate=torus_certificate)
    with pytest.raises(ValueError, match="process noise"):
        SafetyFilterWrapper(make_env(Torus(), **scene, process_noise=0.01), vf, certificate=torus_certificate)
    with pytest.raises(ValueError, match=r"settings do not apply.*kind"):
        SafetyFilterWrapper(make_env(Torus(), **scene), vf, certificate=torus_certificate, kind="smooth")
    other = copy.deepcopy(torus_network)
    with torch.no_grad():
        next(other.parameters()).add_(1e-3)
    with pytest.raises(ValueError, match="a changed model needs a new certificate"):
        SafetyFilterWrapper(make_env(Torus(), **scene), NeuralValueFunction(other), certificate=torus_certificate)


def test_a_stopped_verifier_resumes_to_the_same_result_and_refuses_another_proof(
    network, result, tmp_path, monkeypatch
):
    """A run stopped by its budget, or killed between two saves, continues from its progress file to
    exactly the uninterrupted run's boxes; until then its result claims nothing beyond what was
    decided (the queued boxes are unknown). A file of another level or model is refused."""
    import dataclasses

    import safety.formal.verifier as certify_module

    path = tmp_path / "progress.npz"
    stopped = certify(network, dataclasses.replace(SETTINGS, max_boxes=2 * SETTINGS.batch), resume=path)
    assert not stopped.finished and not stopped.certified
    assert 2 * SETTINGS.batch <= stopped.boxes_handled < result.boxes_handled
    assert int((stopped.status == UNKNOWN).sum()) > 0
    resumed = certify(network, SETTINGS, resume=path)
    assert resumed.finished and resumed.boxes_handled == result.boxes_handled
    assert torch.equal(resumed.lo, result.lo) and torch.equal(resumed.status, result.status)
    assert torch.equal(resumed.backup, result.backup) and resumed.counterexamples == result.counterexamples
    again = certify(network, SETTINGS, resume=path)  # finished: the same result, no box handled again
    assert again.boxes_handled == result.boxes_handled and torch.equal(again.status, result.status)

    killed = tmp_path / "killed.npz"
    saves = []

    def save_then_die(original):
        def save(*args, **kwargs):
            original(*args, **kwargs)
            saves.append(1)
            if len(saves) == 3:
                raise KeyboardInterrupt  # as if killed right after the third save

        return save

    monkeypatch.setattr(certify_module, "SAVE_EVERY_S", 0.0)  # a save before every batch
    monkeypatch.setattr(certify_module, "save_progress", save_then_die(certify_module.save_progress))
    with pytest.raises(KeyboardInterrupt):
        certify(network, SETTINGS, resume=killed)
    monkeypatch.undo()
    after_kill = certify(network, SETTINGS, resume=killed)
    assert torch.equal(after_kill.lo, result.lo) and torch.equal(after_kill.status, result.status)

    junk = tmp_path / "junk.npz"
    arrays = ("queue_lo", "queue_hi", "done_lo", "done_hi", "done_status", "done_backup", "kept_lo", "kept_hi")
    arrays += ("inputs", "outside_lo", "outside_hi")
    np.savez(junk, header=np.array("[1, 2]"), **{k: np.zeros(1) for k in arrays})  # JSON, but not a header
    with pytest.raises(ValueError, match="not a verifier progress file"):
        certify(network, SETTINGS, resume=junk)
    with pytest.raises(ValueError, match="not a reach certificate file"):
        check_certificate(junk, network)
    with pytest.raises(ValueError, match=r"another proof .*level 0\.3, not 0\.4"):
        certify(network, dataclasses.replace(SETTINGS, level=0.4), resume=path)
    other = copy.deepcopy(network)
    with torch.no_grad():
        next(other.parameters()).add_(1e-3)
    with pytest.raises(ValueError, match="another value function"):
        certify(other, SETTINGS, resume=path)


def test_every_field_of_a_certificate_file_is_checked_and_a_damaged_file_named(
    torus_network, torus_certificate, tmp_path
):
    """A certificate is data from outside: a NaN or infinite input or corner, a bad resolution or level,
    a truncated or bit-flipped file and a FIFO are refused naming the file (NaN used to pass the range
    check ``(u < low) | (u > high)``, and the certified filter then applied a NaN input)."""
    import dataclasses

    from safety.formal.certificate import load_certificate
    from safety.formal.certified_filter import CertifiedFilter
    from safety.formal.checker import verify_certificate

    path = save_certificate(tmp_path / "torus.npz", torus_certificate)
    with np.load(path) as data:
        arrays = dict(data)
    header = json.loads(str(arrays["header"]))

    def bad(name: str, **changed) -> str:
        out = tmp_path / f"{name}.npz"
        np.savez(out, **dict(arrays, **changed))
        return str(out)

    nan_input = arrays["inputs"].copy()
    nan_input[0, 0] = np.nan
    inf_corner = arrays["kept_hi"].copy()
    inf_corner[-1, 0] = np.inf
    nan_corner = arrays["kept_lo"].copy()
    nan_corner[0, -1] = np.nan
    cases = [
        (bad("nan_input", inputs=nan_input), "a backup input is not finite"),
        (bad("inf_corner", kept_hi=inf_corner), "a kept box has a corner that is not finite"),
        (bad("nan_corner", kept_lo=nan_corner), "a kept box has a corner that is not finite"),
        (bad("short_inputs", inputs=arrays["inputs"][:-1]), "not one row per kept box"),
        (bad("resolution", header=np.array(json.dumps(dict(header, resolution=2.5)))), "resolution 2.5"),
    ]
    nan_level = dict(header, settings={**header["settings"], "level": math.nan})
    cases.append((bad("level", header=np.array(json.dumps(nan_level))), "level must be finite"))
    for where, message in cases:
        with pytest.raises(ValueError, match=message) as refused:
            load_certificate(where)
        assert str(refused.value).startswith(where)
    raw = path.read_bytes()
    (tmp_path / "truncated.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"truncated\.npz: not a reach certificate file, or a damaged one"):
        load_certificate(tmp_path / "truncated.npz")
    for at in range(len(raw) // 4, len(raw), max(1, len(raw) // 16)):  # a flipped bit anywhere in the data
        flipped = bytearray(raw)
        flipped[at] ^= 0x10
        (tmp_path / "flipped.npz").write_bytes(bytes(flipped))
        try:
            load_certificate(tmp_path / "flipped.npz")
        except ValueError as err:
            assert str(err).startswith(str(tmp_path / "flipped.npz")), err
    os.mkfifo(tmp_path / "fifo.npz")
    with pytest.raises(ValueError, match="FIFO"):  # refused without opening it (opening would block)
        load_certificate(tmp_path / "fifo.npz")
    # a certificate made in memory with a NaN input is refused by the checker and the certified filter
    poisoned = dataclasses.replace(torus_certificate, inputs=torch.as_tensor(nan_input))
    with pytest.raises(ValueError, match="a backup input is not finite"):
        verify_certificate(poisoned, torus_network)
    with pytest.raises(ValueError, match="a backup input is not finite"):
        CertifiedFilter(poisoned, torus_network, verify=False)


def test_a_certify_run_that_cannot_fit_or_write_is_refused_before_it_starts(network, tmp_path, capsys):
    """Size before work, and where the result goes: each refused in one line before any box is bounded."""
    import time

    from reach_cli import main
    from training import save_checkpoint

    source = tmp_path / "air3d.pt"
    save_checkpoint(source, network.float())
    (tmp_path / "folder.npz").mkdir()
    (tmp_path / "a-file").write_text("not a folder")
    base = ["certify", str(source), "--level", "0.3", "--dt", "0.05"]
    narrow = ["--closure-scale", "1", "--closure-refinements", "0"]  # not Air3D's wide, refined defaults
    progress = tmp_path / "p.npz"
    for extra, message in (
        (["--disturbance-splits", "100000", "--out", str(tmp_path / "a.npz")], "GiB, but"),
        (["--min-width", "1e-12", "--out", str(tmp_path / "a.npz")], "beyond what a 64-bit index holds"),
        (["--closure-width", "1e-5", *narrow, "--out", str(tmp_path / "a.npz")], "closure cover cut down to"),
        (["--out", str(tmp_path / "folder.npz")], "is a directory"),
        (["--out", str(tmp_path / "a-file" / "c.npz")], "--out path"),  # its folder cannot be made
        (["--out", str(progress), "--resume", str(progress)], "name the same file"),
    ):
        start = time.monotonic()
        assert main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and message in err, err
        assert time.monotonic() - start < 30
    assert not (tmp_path / "a.npz").exists() and not progress.exists()
    for source_text in (f"min:{source},{source}",):
        assert main(["certify", source_text, "--level", "0.3", "--out", str(tmp_path / "m.npz")]) == 2
        err = capsys.readouterr().err.strip()
        assert "certify takes a neural value function" in err and err.count("\n") == 0, err
