"""The escape set of a formal certificate: next states that leave the domain, treated soundly.

A user system whose flow carries every state out of the domain: without an escape set nothing can
be certified (every trajectory leaves the box where the value function is defined); with one, the
states that are far from failure need no network at all, and the certified set is most of the box.
The value function is the failure margin itself (a ``diff`` network with a zero output layer), so
what is proven is plain geometry and every claim can be checked at samples.
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from reach.integrators import make_stepper
from reach.systems import Air3D, ControlAffineSystem, Dubins3D
from reach.systems.arrays import TORCH
from reach.systems.box import Box
from safety.formal.certificate import save_certificate
from safety.formal.certified_filter import CertifiedFilter
from safety.formal.checker import check_certificate
from safety.formal.closure import certified_set, closure_cover, closure_rows
from safety.formal.settings import ESCAPE, CertifySettings, escape_rule
from safety.formal.verifier import Verifier, certify, value_bounds
from training.network import ValueNetwork

PUSH, GUST, RADIUS = 0.1, 0.05, 0.25


class Outflow(ControlAffineSystem):
    """A point blown away from the centre of ``[-1, 1]^2`` (``p' = p + u + d``), steered by
    ``|u_i| <= 0.1`` against gusts ``|d_i| <= 0.05``, that must keep out of a disc of radius 0.25 at
    the centre. Every trajectory leaves the box, far from the disc."""

    name = "outflow-avoid"
    state_names = ("px", "py")
    periodic = (False, False)

    def __init__(self, horizon: float = 1.0) -> None:
        self.horizon = horizon
        self.domain = ((-1.0, 1.0), (-1.0, 1.0))
        self.control_bounds = Box.symmetric([PUSH, PUSH])
        self.disturbance_bounds = Box.symmetric([GUST, GUST])

    def parameters(self) -> dict:
        return {"horizon": self.horizon}

    def drift(self, x, xp):
        return [x[0], x[1]]

    def control_matrix(self, x, xp):
        return {(0, 0): 1.0, (1, 1): 1.0}

    def disturbance_matrix(self, x, xp):
        return {(0, 0): 1.0, (1, 1): 1.0}

    def failure_margin_columns(self, x, xp):
        return xp.sqrt(x[0] ** 2 + x[1] ** 2) - RADIUS

    def margin_step_bound(self, dt: float, integrator: str) -> float:
        """For ``p' = p + w`` (``w = u + d`` held) a step gives ``p_next = a p + b dt w`` with ``a >= 1``
        and ``b = 1`` (Euler) or ``1 + dt/2 + dt^2/6 + dt^3/24`` (RK4): ``|p|`` drops by at most
        ``b dt |w|``, and ``l`` is ``|p|`` less a constant."""
        b = 1.0 if integrator == "euler" else 1 + dt / 2 + dt**2 / 6 + dt**3 / 24
        return b * dt * math.hypot(PUSH + GUST, PUSH + GUST)

    def margin_outside_domain(self, scale: float = 1.0) -> float:
        return scale - RADIUS


def margin_network(system: ControlAffineSystem) -> ValueNetwork:
    """``V = l`` exactly: a ``diff`` network (``V = l + scale * output``) whose output layer is zero."""
    torch.manual_seed(0)
    network = ValueNetwork(system, "ssl", width=8, w0=3.0, parameterisation="diff")
    with torch.no_grad():
        network.output.weight.zero_()
        network.output.bias.zero_()
    return network


LEVEL, DT = 0.1, 0.05
BASE = {"level": LEVEL, "time_to_go": 1.0, "dt": DT, "initial_splits": 8, "min_relative_width": 1 / 64}


@pytest.fixture(scope="module")
def outflow() -> ValueNetwork:
    return margin_network(Outflow())


@pytest.fixture(scope="module")
def with_escape(outflow):
    result = certify(outflow, CertifySettings(**BASE, escape_margin=0.6))
    return result, certified_set(outflow, result)


def test_without_an_escape_set_the_flow_leaves_nothing_certified(outflow):
    result = certify(outflow, CertifySettings(**BASE))
    certificate = certified_set(outflow, result)
    assert len(certificate.kept.lo) == 0


def test_with_one_most_of_the_box_is_certified_and_its_file_checks(outflow, with_escape, tmp_path):
    result, certificate = with_escape
    domain = Outflow().domain_tensor(torch.float64, "cpu")
    shares = result.volume_shares()
    assert shares["escape"] > 0.1 and result.band_open == 0
    assert certificate.settings.escape_margin == 0.6  # E held
    kept = certificate.kept_volume_share(domain)
    escape = float(((certificate.escape.hi - certificate.escape.lo) / 2.0).prod(-1).sum())
    assert kept > 0.2 and kept + escape > 0.6, (kept, escape)
    path = save_certificate(tmp_path / "outflow.npz", certificate)
    check_certificate(path, outflow)


def in_certified_set(certificate, system, x: torch.Tensor) -> torch.Tensor:
    """``(kept boxes) ∪ E`` at states ``x``, evaluated directly."""
    margin = system.failure_margin(x)
    beyond = ((x < -1.0) | (x > 1.0)).any(-1)
    lo, hi = certificate.kept.lo, certificate.kept.hi
    in_kept = ((x[:, None, :] >= lo) & (x[:, None, :] <= hi)).all(-1).any(-1)
    return beyond | (margin >= certificate.settings.escape_margin) | in_kept


def test_the_certified_filter_keeps_every_trajectory_safe_in_and_beyond_the_domain(outflow, with_escape):
    """From 256 certified states, 80 steps of random nominal inputs (toward the disc, and some not
    admissible) and random gusts through the filter: every state stays in the certified set, in the
    box or beyond it, and out of the disc; some inputs are replaced."""
    _, certificate = with_escape
    system = Outflow()
    filt = CertifiedFilter(certificate, outflow)
    step = make_stepper(system, DT, "euler", TORCH)
    g = torch.Generator().manual_seed(4)
    x = -1.0 + 2.0 * torch.rand((4000, 2), generator=g, dtype=torch.float64)
    x = x[in_certified_set(certificate, system, x)][:256]
    assert len(x) == 256
    interventions = 0
    for _ in range(80):
        toward = -0.12 * x / x.norm(dim=-1, keepdim=True)  # some beyond the control box
        nominal = toward + 0.02 * torch.randn(x.shape, generator=g, dtype=torch.float64)
        applied, info = filt(x, nominal)
        assert bool(info.certified.all())
        interventions += int(info.intervened.sum())
        d = GUST * (2.0 * torch.rand(x.shape, generator=g, dtype=torch.float64) - 1.0)
        x = TORCH.stack(step(TORCH.unbind(x), TORCH.unbind(applied), TORCH.unbind(d)))
        assert bool(in_certified_set(certificate, system, x).all())
        assert bool((system.failure_margin(x) > 0).all())
    assert interventions > 0
    assert bool(((x < -1.0) | (x > 1.0)).any(-1).any())  # the flow took some beyond the domain


def test_the_checker_refuses_an_escape_set_that_does_not_hold(outflow, with_escape, tmp_path):
    _, certificate = with_escape
    path = save_certificate(tmp_path / "outflow.npz", certificate)
    with np.load(path) as data:
        arrays = dict(data)
    header = json.loads(str(arrays["header"]))

    def variant(name: str, **changes) -> str:
        out = tmp_path / f"{name}.npz"
        np.savez(out, **(arrays | changes))
        return str(out)

    # E above the least margin beyond the domain: refused before anything is bounded
    header["settings"]["escape_margin"] = 0.8
    with pytest.raises(ValueError, match=r"above 0\.75"):
        check_certificate(variant("high", header=np.array(json.dumps(header))), outflow)
    # a lower E, still sound (every state of its band is kept) ...
    header["settings"]["escape_margin"] = 0.3
    check_certificate(variant("lower", header=np.array(json.dumps(header))), outflow)
    # ... but not this low: its band (0.005 - delta <= l < 0.005) reaches into the disc, where no box is kept
    header["settings"]["escape_margin"] = 0.005
    with pytest.raises(ValueError, match="band"):
        check_certificate(variant("lowest", header=np.array(json.dumps(header))), outflow)
    # a kept box of the band dropped into the excluded rest
    band = Outflow().failure_margin(0.5 * torch.from_numpy(arrays["kept_lo"] + arrays["kept_hi"])) > 0.5
    i = int(band.nonzero()[0])
    moved = variant(
        "moved",
        kept_lo=np.delete(arrays["kept_lo"], i, 0),
        kept_hi=np.delete(arrays["kept_hi"], i, 0),
        inputs=np.delete(arrays["inputs"], i, 0),
        excluded_lo=np.concatenate([arrays["excluded_lo"], arrays["kept_lo"][i : i + 1]]),
        excluded_hi=np.concatenate([arrays["excluded_hi"], arrays["kept_hi"][i : i + 1]]),
    )
    with pytest.raises(ValueError, match="box meeting the band below the escape set is not kept"):
        check_certificate(moved, outflow)
    # a kept box missing: the file's boxes no longer tile the state box
    missing = variant(
        "missing", kept_lo=arrays["kept_lo"][1:], kept_hi=arrays["kept_hi"][1:], inputs=arrays["inputs"][1:]
    )
    with pytest.raises(ValueError, match="do not tile the state box"):
        check_certificate(missing, outflow)
    # settings the verifier does not know: refused as a whole, in one line
    junk = dict(header, settings={**header["settings"], "shortcut": True})
    with pytest.raises(ValueError, match="its settings are not a verifier's"):
        check_certificate(variant("junk", header=np.array(json.dumps(junk))), outflow)
    # escape boxes without an escape set
    header["settings"]["escape_margin"] = None
    with pytest.raises(ValueError, match="escape boxes but"):
        check_certificate(variant("none", header=np.array(json.dumps(header))), outflow)


def test_systems_without_the_lemmas_are_refused_naming_what_is_missing():
    network = ValueNetwork(Air3D(), "ssl", width=8, w0=3.0)
    with pytest.raises(ValueError, match="no bound on how much one rk4 step"):
        certify(network, CertifySettings(level=0.1, time_to_go=1.0, dt=0.02, integrator="rk4", escape_margin=0.7))
    with pytest.raises(ValueError, match="escape_margin"):
        CertifySettings(level=0.1, time_to_go=1.0, dt=0.02, escape_margin=-1.0)


@settings(max_examples=60, deadline=None)
@given(
    system=st.sampled_from([Air3D(), Dubins3D(set_mode="avoid"), Outflow()]),
    integrator=st.sampled_from(["euler", "rk4"]),
    scale=st.sampled_from([0.5, 1.0, 10.0, 1e3]),
    seed=st.integers(0, 2**16),
)
def test_the_escape_lemmas_hold_at_sampled_states_far_beyond_the_domain(system, integrator, scale, seed):
    """``l(step) >= l(x) - delta`` from states up to ``scale`` times the domain, every input and
    disturbance sampled (vertices included); states beyond the domain have ``l >= margin_outside``."""
    dt = 0.05
    delta = system.margin_step_bound(dt, integrator)
    if delta is None:
        assert isinstance(system, Air3D) and integrator == "rk4"
        return
    g = torch.Generator().manual_seed(seed)
    domain = system.domain_tensor(torch.float64, "cpu")
    x = domain[:, 0] + (domain[:, 1] - domain[:, 0]) * torch.rand(
        (2048, system.state_dim), generator=g, dtype=torch.float64
    )
    periodic = torch.tensor(system.periodic)
    x = torch.where(periodic, x, x * scale)
    box = system.control_bounds
    low, high = torch.tensor(box.low, dtype=torch.float64), torch.tensor(box.high, dtype=torch.float64)
    u = low + (high - low) * torch.randint(0, 3, (len(x), len(low)), generator=g).double() / 2
    cols_d: list = []
    if system.disturbance_dim:
        dbox = system.disturbance_bounds
        dlo, dhi = torch.tensor(dbox.low, dtype=torch.float64), torch.tensor(dbox.high, dtype=torch.float64)
        cols_d = TORCH.unbind(dlo + (dhi - dlo) * torch.randint(0, 3, (len(x), len(dlo)), generator=g).double() / 2)
    step = make_stepper(system, dt, integrator, TORCH)
    nxt = TORCH.stack(step(TORCH.unbind(x), TORCH.unbind(u), cols_d))
    drop = system.failure_margin(x) - system.failure_margin(nxt)
    assert float(drop.max()) <= delta * (1 + 1e-9) + 1e-9 * scale
    beyond = (((x < domain[:, 0]) | (x > domain[:, 1])) & ~periodic).any(-1)
    assert bool((system.failure_margin(x)[beyond] >= system.margin_outside_domain()).all())


def test_an_escape_rule_of_a_shipped_system_names_its_numbers():
    assert escape_rule(Air3D(), CertifySettings(level=0.1, time_to_go=1.0, dt=0.02, escape_margin=0.72)) == (
        0.72,
        pytest.approx(0.03),
    )
    with pytest.raises(ValueError, match=r"above 0\.75"):
        escape_rule(Air3D(), CertifySettings(level=0.1, time_to_go=1.0, dt=0.02, escape_margin=0.76))
    assert ESCAPE == 4


def test_the_command_line_takes_an_escape_margin_and_refuses_a_bad_one(tmp_path, capsys):
    from reach_cli import main
    from training import save_checkpoint

    torch.manual_seed(0)
    source = tmp_path / "air3d.pt"
    save_checkpoint(source, ValueNetwork(Air3D(), "ssl", width=16, w0=3.0))
    out = tmp_path / "cert.npz"
    args = ["certify", str(source), "--level", "0.3", "--dt", "0.05", "--initial-splits", "4", "--min-width", "0.125"]
    args += ["--closure-refinements", "0"]  # not Air3D's refined defaults
    # the network's own box (Air3D's defaults close over a box four times wider)
    own_box = ["--closure-scale", "1", "--escape-margin", "0.7", "--closure-width", "0.0625"]
    assert main([*args, *own_box, "--out", str(out)]) in (0, 3)
    printed = capsys.readouterr().out
    assert "wrote" in printed and ("escape set" in printed), printed
    assert main(["certify", str(source), "--check", str(out)]) == 0
    for bad, named in (
        ([*args, "--closure-scale", "1", "--escape-margin", "0.9", "--out", str(out)], "above 0.75"),
        ([*args, "--escape-margin", "0.7", "--integrator", "rk4", "--out", str(out)], "margin_step_bound"),
        ([*args, "--closure-width", "0", "--out", str(out)], "closure_relative_width"),
        ([*args, "--closure-scale", "3", "--closure-width", "0.125", "--out", str(out)], "power of two"),
    ):
        assert main(bad) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and named in err, err
    for option, value in (("--closure-refinements", "-1"), ("--closure-refine-reach", "0")):
        with pytest.raises(SystemExit) as stop:  # argparse refuses it, naming the option
            main([*args, option, value, "--out", str(out)])
        assert stop.value.code == 2 and f"argument {option}: must be" in capsys.readouterr().err


def test_boxes_of_the_band_are_split_finer_until_they_hold_only_states_of_the_set(outflow, tmp_path):
    """At ``c = 0.5`` the band below ``E = {l >= 0.6}`` lies just above the level: boxes of the first
    cover that meet it also hold states with ``V < c``, so ``S_c ∪ E`` is not proven (``band_open``).
    The certified set is the union of kept boxes, so such boxes may be kept whole and ``E`` still
    holds. Split to 1/64 there, while the rest stops at 1/8, every band box proves ``V >= c``."""
    coarse = {**BASE, "level": 0.5, "min_relative_width": 1 / 8, "escape_margin": 0.6}
    result = certify(outflow, CertifySettings(**coarse))
    assert result.band_open > 0 and not result.certified
    certificate = certified_set(outflow, result)
    assert certificate.settings.escape_margin == 0.6
    lo, hi = certificate.kept.lo, certificate.kept.hi
    band = Verifier(outflow, certificate.settings, torch.device("cpu")).in_band(lo, hi)
    below = value_bounds(copy.deepcopy(outflow).double(), lo[band], hi[band], 1.0).lo < 0.5
    assert bool(below.any())  # kept band boxes that hold states of V < c
    check_certificate(save_certificate(tmp_path / "coarse.npz", certificate), outflow)
    fine = certify(outflow, CertifySettings(**coarse, band_min_relative_width=1 / 64))
    assert fine.band_open == 0
    widths = ((fine.hi - fine.lo) / 2.0).amax(-1)
    assert float(widths.min()) < 1 / 8 and float(widths.max()) == 1 / 8
    certificate = certified_set(outflow, fine)
    assert certificate.settings.escape_margin == 0.6 and len(certificate.kept.lo) > 0


def test_an_escape_set_whose_band_cannot_be_kept_is_dropped(outflow, tmp_path):
    """With ``E = {l >= 0.005}`` the band below it reaches into the disc, where no box can be kept, so
    ``E`` does not hold: the closure is computed without it, nothing leans on it, and the file checks
    so (the flow carries every state out of the box, so nothing is kept)."""
    result = certify(outflow, CertifySettings(**BASE, escape_margin=0.005))
    without = certified_set(outflow, result)
    assert without.settings.escape_margin is None and len(without.escape.lo) == 0
    assert len(without.kept.lo) == 0
    check_certificate(save_certificate(tmp_path / "without.npz", without), outflow)


def test_after_a_refinement_e_holds_only_while_every_box_of_its_band_can_stay(outflow, with_escape):
    """A refinement's closure asks only about the new parts, besides the boxes that stay: a box of
    the band that is neither (dropped before, and not cut) can no longer be kept, so ``E`` is not
    assumed; with every band box staying, it is."""
    from dataclasses import replace

    result, _ = with_escape
    verifier = Verifier(outflow, result.settings, torch.device("cpu"), closure=True)
    cover, grid = closure_cover(result, verifier)
    cover = replace(cover, backup=cover.backup.clone())  # the module's fixture stays as it was
    band = verifier.in_band(cover.lo, cover.hi) & (cover.status != ESCAPE)
    assert bool(band.any())
    nothing = torch.zeros(len(band), dtype=torch.bool)
    assert closure_rows(verifier, grid, cover, None, band, (nothing, nothing)) is None
    closed = closure_rows(verifier, grid, cover, None, band, None)
    assert closed is not None
    stay = torch.zeros(len(band), dtype=torch.bool)
    stay[closed[0]] = True
    cover.backup[closed[0]] = closed[1]
    again = closure_rows(verifier, grid, cover, None, band, (stay, nothing))
    assert again is not None and set(again[0].tolist()) == set(closed[0].tolist())


def test_a_progress_file_of_another_escape_set_is_refused(outflow, tmp_path):
    """The escape margin decides which boxes are proven, so a stopped run resumes only under the same one."""
    progress = tmp_path / "progress.npz"
    stopped = certify(outflow, CertifySettings(**BASE, escape_margin=0.6, max_boxes=64), resume=progress)
    assert not stopped.finished and not stopped.certified
    with pytest.raises(ValueError, match=r"another proof.*escape_margin"):
        certify(outflow, CertifySettings(**BASE, escape_margin=0.7), resume=progress)
    resumed = certify(outflow, CertifySettings(**BASE, escape_margin=0.6), resume=progress)
    assert resumed.finished and resumed.boxes_handled > stopped.boxes_handled


def test_a_closure_over_a_wider_box_keeps_boxes_beyond_the_networks(outflow, tmp_path):
    """``closure_scale=2``: the closure runs over ``[-2, 2]^2`` with ``E = {l >= 1.7}`` beyond it, and
    boxes beyond the network's box are kept by where their next states land, never by the network.
    The certificate checks, keeps boxes beyond the network's box, and the filter certifies a state
    there; a scale that is not a power of two, one without cells, or an escape margin above the wide
    box's bound are refused."""
    wide = {**BASE, "closure_scale": 2, "closure_relative_width": 1 / 16}
    certificate = certified_set(outflow, certify(outflow, CertifySettings(**wide, escape_margin=1.7)))
    assert certificate.settings.escape_margin == 1.7
    assert bool(((certificate.kept.lo < -1) | (certificate.kept.hi > 1)).any(-1).any())
    assert float(certificate.kept.hi.abs().max()) == 2.0
    domain = Outflow().domain_tensor(torch.float64, "cpu")
    inner = ~((certificate.kept.lo < -1) | (certificate.kept.hi > 1)).any(-1)
    share = float(((certificate.kept.hi - certificate.kept.lo)[inner] / 2.0).prod(-1).sum())
    assert certificate.kept_volume_share(domain) == pytest.approx(share) and share <= 1.0  # the box's share only
    assert certificate.kept_beyond(domain) == int((~inner).sum()) > 0
    check_certificate(save_certificate(tmp_path / "wide.npz", certificate), outflow)
    _, info = CertifiedFilter(certificate, outflow)(torch.tensor([[1.5, 0.3]], dtype=torch.float64), torch.zeros(2))
    assert bool(info.certified[0])
    with pytest.raises(ValueError, match="power of two"):
        CertifySettings(**{**wide, "closure_scale": 3})
    with pytest.raises(ValueError, match="needs closure_relative_width"):
        CertifySettings(**BASE, closure_scale=2)
    with pytest.raises(ValueError, match=r"above 1\.75"):
        certify(outflow, CertifySettings(**wide, escape_margin=1.8))

    class Unscaled(Outflow):  # a user's lemma written before closures over wider boxes
        def margin_outside_domain(self) -> float:
            return 1.0 - RADIUS

    with pytest.raises(ValueError, match="margin_outside_domain takes no scale"):
        escape_rule(Unscaled(), CertifySettings(**wide, escape_margin=0.6), 2)
    assert escape_rule(Unscaled(), CertifySettings(**BASE, escape_margin=0.6)) == (0.6, pytest.approx(0.0106, abs=1e-4))
