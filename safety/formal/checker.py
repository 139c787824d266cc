"""The independent checker of a certificate file, and the landing rule it shares with the certified filter.

:func:`check_certificate` re-verifies a certificate file (:mod:`safety.formal.certificate`) from the
file alone, with none of the verifier's search and none of the closure's: the fingerprint, system and
settings must match; every outside box must bound ``V < c``; every kept box must bound ``l > 0``; and
with its stored input, each of its next-state pieces must lie within the kept boxes, or have
``V >= c`` and lie within the kept and outside boxes. With an escape set ``E``, a piece all in ``E``
needs nothing, the escape boxes must lie in ``E``, the file's boxes must tile the state box, and
every box meeting the band below ``E`` must be kept. The checker reuses the bounds
(:mod:`safety.formal.linear_bounds`, :mod:`safety.formal.intervals`, through
:class:`safety.formal.verifier.Verifier`), not the search.

"Within the boxes" is looked up on the certificate's cell grid (:class:`CertificateCells`), held
sparsely (:class:`safety.formal.cover.DyadicCover`), so the check's cost grows with the boxes, not
with the grid's cells. :func:`landing_verdicts` is the one implementation of the landing rule: the
checker names the first condition that fails, the certified filter asks whether all hold.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import torch

from safety.formal.certificate import Certificate, check_fields, load_certificate
from safety.formal.cover import CellGrid, DyadicCover
from safety.formal.intervals import Interval
from safety.formal.verifier import Verifier, margin_bounds, network_of
from training.checkpoint import network_digest
from training.network import NeuralValueFunction, ValueNetwork

__all__ = [
    "CHECK_CHUNK",
    "CertificateCells",
    "LandingVerdicts",
    "check_certificate",
    "check_provenance",
    "landing_verdicts",
    "verify_certificate",
]

#: boxes whose value bounds the checker computes at once (its memory grows with the network's width)
CHECK_CHUNK = 65536


def check_certificate(
    path: str | Path, value_function: NeuralValueFunction | ValueNetwork, device: str | torch.device = "cpu"
) -> Certificate:
    """Re-verify a certificate file for ``value_function`` from the file alone (module docstring),
    bounding the network on ``device``. Raises ``ValueError`` naming the first thing that does not
    hold; returns the certificate."""
    certificate = load_certificate(path)
    verify_certificate(certificate, value_function, str(path), device)
    return certificate


def _value_bounds(verifier: Verifier, lo: torch.Tensor, hi: torch.Tensor) -> Interval:
    """Bounds of ``V`` over boxes, ``CHECK_CHUNK`` boxes at a time on the verifier's device (a
    certificate holds up to millions of boxes), returned on the CPU."""
    device = verifier.domain.device
    chunks = [
        verifier.value(lo[start : start + CHECK_CHUNK].to(device), hi[start : start + CHECK_CHUNK].to(device))
        for start in range(0, len(lo), CHECK_CHUNK)
    ]
    if not chunks:
        none = torch.zeros(0, dtype=torch.float64)
        return Interval(none, none)
    return Interval(torch.cat([c.lo.cpu() for c in chunks]), torch.cat([c.hi.cpu() for c in chunks]))


def check_provenance(certificate: Certificate, network: ValueNetwork, path: str) -> None:
    """Refuse a certificate of another system or another value function, naming which."""
    provenance = certificate.provenance
    if network.system.config() != provenance.system:
        theirs, ours = provenance.system.get("name"), network.system.config()["name"]
        what = f"{theirs}, not {ours}" if theirs != ours else f"{ours} with other parameters ({provenance.system})"
        raise ValueError(f"{path}: certifies {what}")
    digest = network_digest(network)
    if digest != provenance.fingerprint:
        raise ValueError(
            f"{path}: certifies the value function {provenance.fingerprint[:12]}..., not this one ({digest[:12]}...): "
            "a changed model needs a new certificate"
        )


def verify_certificate(
    certificate: Certificate,
    value_function: NeuralValueFunction | ValueNetwork,
    path: str = "the certificate",
    device: str | torch.device = "cpu",
) -> None:
    """Re-verify ``certificate`` for ``value_function`` (what :func:`check_certificate` does after
    reading); the network's bounds are computed on ``device``, everything else on the CPU."""
    check_fields(certificate, path)
    network = network_of(value_function)
    check_provenance(certificate, network, path)
    settings = certificate.settings
    verifier = Verifier(network, settings, torch.device("cpu"), closure=True)
    on_device = (
        verifier
        if torch.device(device).type == "cpu"
        else Verifier(network, settings, torch.device(device), closure=True)
    )
    domain = verifier.domain
    grid = CellGrid(domain, certificate.resolution)
    if verifier.escape is None and len(certificate.escape):
        raise ValueError(f"{path}: it has escape boxes but its settings no escape set")
    for name, boxes in (("kept", certificate.kept), ("outside", certificate.outside),
                        ("escape", certificate.escape), ("excluded", certificate.excluded)):  # fmt: skip
        lo, hi = boxes.lo, boxes.hi
        if lo.ndim != 2 or lo.shape != hi.shape or lo.shape[-1] != domain.shape[0]:
            raise ValueError(f"{path}: its {name} boxes have shape {tuple(lo.shape)}")
        if not bool(((lo >= domain[:, 0] - 1e-12) & (hi <= domain[:, 1] + 1e-12) & (lo <= hi)).all()):  # NaN fails
            raise ValueError(f"{path}: a {name} box is not a box inside the domain")
        grid.cells(lo, hi, exact=True)
    every = certificate.every_box()
    try:
        grid = CellGrid(domain, certificate.resolution, every.lo, every.hi)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    outside = certificate.outside
    if not bool(verifier.in_network_domain(outside.lo, outside.hi).all()):
        raise ValueError(f"{path}: an outside box lies beyond the network's box, where it has no bounds")
    if bool((_value_bounds(on_device, outside.lo, outside.hi).hi >= settings.level).any()):
        raise ValueError(f"{path}: an outside box is not proven to hold only V < {settings.level:g}")
    lo, hi, u = certificate.kept.lo, certificate.kept.hi, certificate.inputs
    control = network.system.control_bounds
    low, high = torch.tensor(control.low, dtype=torch.float64), torch.tensor(control.high, dtype=torch.float64)
    if u.shape != (len(lo), len(control.low)) or not bool(((u >= low) & (u <= high)).all()):  # NaN fails
        raise ValueError(f"{path}: a backup input is missing or outside the control box")
    margin = margin_bounds(network.system, lo, hi)
    if bool((margin.lo <= 0).any()):
        raise ValueError(f"{path}: a kept box is not proven to keep l(x) > 0")
    if verifier.escape is not None:
        _check_escape(certificate, verifier, grid, path)
    cells = CertificateCells.of(certificate, grid)

    def lower(n_lo: torch.Tensor, n_hi: torch.Tensor) -> torch.Tensor:
        return _value_bounds(on_device, n_lo, n_hi).lo

    land = landing_verdicts(verifier, cells, settings.level, lo, hi, u, lower)
    # the conditions one at a time, so that the first that fails is named
    if not bool((land.free | land.inside).all()):
        raise ValueError(f"{path}: a kept box's next states may leave the domain")
    rest = ~land.free & ~land.in_set  # pieces not within the set's boxes: V >= c must show that they
    if not bool(land.in_allowed[rest].all()):  # miss the outside boxes they meet
        raise ValueError(f"{path}: a kept box's next states may leave the certified boxes")
    if not bool(land.in_network[rest].all()):
        raise ValueError(f"{path}: a kept box's next states leave the certified boxes beyond the network's box")
    if not bool(land.value_ok[rest].all()):
        raise ValueError(
            f"{path}: a kept box's next states meet a box outside the set and are not proven to have "
            f"V >= {settings.level:g}"
        )
    assert bool(land.ok().all())  # the same rule as the filter's, as one


@dataclass(frozen=True, eq=False)
class CertificateCells:
    """A certificate's boxes on its cell ``grid`` (edges pinned to every box's corners): a cover of the
    set's boxes (``members``: kept, then escape) and one of the boxes a next state may land in
    (``allowed``: kept, outside, then escape, so that a cell's owner below the number of kept boxes
    is the kept box that holds it)."""

    grid: CellGrid
    members: DyadicCover
    allowed: DyadicCover

    @staticmethod
    def of(certificate: Certificate, grid: CellGrid) -> CertificateCells:
        """The covers of ``certificate``'s boxes on ``grid`` (a :class:`CellGrid` of its ``every_box``)."""
        members, allowed = certificate.member_boxes(), certificate.allowed_boxes()
        return CertificateCells(grid, grid.cover(members.lo, members.hi), grid.cover(allowed.lo, allowed.hi))


class LandingVerdicts(NamedTuple):
    """Per next-state piece of boxes under their inputs (every disturbance piece): the row of (box,
    disturbance piece) it came from (``piece``), and each condition of a certificate's rule."""

    piece: torch.Tensor
    free: torch.Tensor  #: all in the escape set ``E`` (needs nothing more)
    inside: torch.Tensor  #: inside the domain (with ``E``, pieces are cut to it)
    in_set: torch.Tensor  #: within the set's boxes (kept, and escape)
    in_allowed: torch.Tensor  #: within the kept, outside and escape boxes
    in_network: torch.Tensor  #: inside the network's box (where it has bounds)
    value_ok: torch.Tensor  #: ``V >= c`` proven on it (asked only where the rest allows it)

    def ok(self) -> torch.Tensor:
        """Whether each piece lands in the set: in ``E``; or inside the domain and within the set's
        boxes; or within the allowed boxes, inside the network's box, with ``V >= c`` (so it misses
        the outside boxes it meets)."""
        return self.free | (self.inside & (self.in_set | (self.in_allowed & self.in_network & self.value_ok)))


def landing_verdicts(
    verifier: Verifier,
    cells: CertificateCells,
    level: float,
    lo: torch.Tensor,
    hi: torch.Tensor,
    u: torch.Tensor,
    value_lower: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
) -> LandingVerdicts:
    """The certificate's rule for boxes ``[lo, hi]`` under inputs ``u``, piece by piece: one
    implementation for the checker (which names the first condition that fails) and the certified
    filter (point boxes: is the nominal input proven to keep the set?). ``cells`` covers the set's
    boxes and the allowed boxes on the certificate's grid; ``value_lower`` gives lower bounds of
    ``V`` over next-state boxes, and is asked only about pieces that need it."""
    n_lo, n_hi, piece, escaped, _ = verifier.landing(lo, hi, u)
    count = len(n_lo)
    inside = verifier.in_domain(n_lo, n_hi)
    in_set, in_allowed = torch.zeros(count, dtype=torch.bool), torch.zeros(count, dtype=torch.bool)
    ask = ~escaped & inside
    in_set[ask] = _within(cells.grid, cells.members, n_lo[ask], n_hi[ask])
    ask &= ~in_set
    in_allowed[ask] = _within(cells.grid, cells.allowed, n_lo[ask], n_hi[ask])
    in_network = verifier.in_network_domain(n_lo, n_hi)
    value_ok = torch.zeros(count, dtype=torch.bool)
    ask &= in_allowed & in_network
    if bool(ask.any()):
        value_ok[ask] = value_lower(n_lo[ask], n_hi[ask]).cpu() >= level
    return LandingVerdicts(piece, escaped, inside, in_set, in_allowed, in_network, value_ok)


def _within(grid: CellGrid, cover: DyadicCover, n_lo: torch.Tensor, n_hi: torch.Tensor) -> torch.Tensor:
    """Whether each next-state box lies within the cover's cells."""
    return cover.covers(*grid.cells(n_lo.cpu(), n_hi.cpu(), exact=False))


def _check_escape(certificate: Certificate, verifier: Verifier, grid: CellGrid, path: str) -> None:
    """The escape set's own conditions: its boxes lie in ``E``, the file's boxes tile the state box,
    and every box meeting the band below ``E`` is kept (so every state a step from ``E`` may reach
    inside the domain is in the set)."""
    escape = certificate.escape
    if not bool(verifier.in_escape(escape.lo, escape.hi).all()):
        raise ValueError(f"{path}: an escape box is not proven to lie where l >= {verifier.escape[0]:g}")
    every = certificate.every_box()
    a, b = grid.cells(every.lo, every.hi, exact=True)
    whole = torch.zeros(1, grid.n, dtype=torch.long), torch.full((1, grid.n), grid.resolution, dtype=torch.long)
    cells = int((b - a).prod(-1).sum())
    if cells != grid.resolution**grid.n or not bool(DyadicCover(a, b, grid.resolution).covers(*whole).all()):
        raise ValueError(f"{path}: its boxes do not tile the state box (the band below the escape set is unchecked)")
    n_kept = len(certificate.kept)
    band = verifier.in_band(every.lo, every.hi)
    if bool(band[n_kept:].any()):
        raise ValueError(f"{path}: a box meeting the band below the escape set is not kept")
