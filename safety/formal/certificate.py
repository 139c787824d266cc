"""A formally certified safe set from the verifier's boxes, its certificate file, and the checker.

:func:`safety.formal.verifier.certify` proves boxes one at a time: on each **proven** box every state of
``S_c = {V(x, T) >= c}`` is safe and has a backup input that keeps its next state in ``S_c``. Some
boxes stay refuted or unknown, so ``S_c`` itself is not certified. :func:`certified_set` certifies
instead ``S = union of the kept boxes``: every kept box holds no failure state (``l > 0`` on all of
it) and has a backup input under which every next state of the box (every disturbance) lands in a
kept box, or, where the network proves ``V >= c`` on those next states, in a kept box or a box
proven to hold only ``V < c`` (so, in fact, in a kept box). Boxes are dropped until nothing changes
(the largest such union). Then from every state of ``S`` its box's backup input keeps the next state
in ``S``: ``S`` is invariant for all time, and safe.

The network's level set guides where the cover is fine and which inputs are tried first; the set
itself is a union of boxes, not ``S_c``. A certificate made when ``S`` was ``S_c ∩ (kept boxes)``
proves the larger union too (its kept boxes' next states were all shown to be in kept boxes with
``V >= c``), so older files check and mean the union.

The **certificate file** (``.npz``, read with ``allow_pickle=False``: loading runs no code) holds the
kept boxes with their backup inputs, the boxes proven outside ``S_c``, the settings, the system, and
the value function's fingerprint. :func:`check_certificate` re-verifies it from the file alone, with
none of the verifier's search: the fingerprint, system and settings must match; every outside box
must bound ``V < c``; every kept box must bound ``l > 0``; and with its stored input, each of its
next-state pieces must lie within the kept boxes, or have ``V >= c`` and lie within the kept and
outside boxes. The checker reuses the bounds
(:mod:`safety.formal.linear_bounds`, :mod:`safety.formal.intervals`), not the search.

Closure is checked on the cell grid of the boxes (the verifier's cover is dyadic), held sparsely by
:class:`safety.formal.cover.DyadicCover`: its cost grows with the boxes, not with the ``R**n`` cells,
so the 6D and 9D systems' covers are checked as Air3D's are (grids up to ``2**62`` cells). The
closure finds once which boxes each next-state piece meets (the owner of each of its cells, from a
dense table where the grid is small enough, :class:`safety.formal.cover.DenseOwner`), so that a
round costs one pass over those pairs, whatever the grid. With ``closure_refinements`` the cover
then grows finer near the set's edge and the closure runs again (:func:`_split_at_edge`).
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from reach.atomic import atomic_path
from safety.formal.cover import DenseOwner, DyadicCover, cells_in, cover_of, owner_of
from safety.formal.intervals import Interval
from safety.formal.verifier import (
    ESCAPE,
    OUTSIDE,
    PROVEN,
    UNKNOWN,
    CertificationResult,
    CertifySettings,
    _network,
    _Verifier,
    margin_bounds,
)
from training.checkpoint import network_digest
from training.network import NeuralValueFunction, ValueNetwork

__all__ = [
    "Certificate",
    "LandingVerdicts",
    "certified_set",
    "check_certificate",
    "landing_verdicts",
    "load_certificate",
    "save_certificate",
    "volume_share",
]

FORMAT = "reach-certificate/1"


class Certificate:
    """A certified set: ``kept`` boxes (``S`` is their union) with their backup inputs,
    ``outside`` boxes (``V < c`` on each), the grid ``resolution`` per dimension, and provenance.
    With an escape set (``settings.escape_margin``): the ``escape`` boxes (all in ``E``) and the
    ``excluded`` rest of the cover, so that the file's boxes tile the state box and the checker can
    see that every box meeting the band below ``E`` is kept."""

    def __init__(
        self,
        settings: CertifySettings,
        system: dict,
        fingerprint: str,
        kept_lo: torch.Tensor,
        kept_hi: torch.Tensor,
        inputs: torch.Tensor,
        outside_lo: torch.Tensor,
        outside_hi: torch.Tensor,
        resolution: int,
        escape_lo: torch.Tensor | None = None,
        escape_hi: torch.Tensor | None = None,
        excluded_lo: torch.Tensor | None = None,
        excluded_hi: torch.Tensor | None = None,
    ) -> None:
        self.settings, self.system, self.fingerprint = settings, system, fingerprint
        self.kept_lo, self.kept_hi, self.inputs = kept_lo, kept_hi, inputs
        self.outside_lo, self.outside_hi = outside_lo, outside_hi
        self.resolution = resolution
        none = kept_lo.new_zeros((0, kept_lo.shape[-1]))
        self.escape_lo = none if escape_lo is None else escape_lo
        self.escape_hi = none if escape_hi is None else escape_hi
        self.excluded_lo = none if excluded_lo is None else excluded_lo
        self.excluded_hi = none if excluded_hi is None else excluded_hi

    def allowed_boxes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The boxes a kept box's next states may land in: kept first, then outside, then escape."""
        return (
            torch.cat([self.kept_lo, self.outside_lo, self.escape_lo]),
            torch.cat([self.kept_hi, self.outside_hi, self.escape_hi]),
        )

    def every_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Every box the file holds: kept, outside, escape and excluded."""
        return (
            torch.cat([self.kept_lo, self.outside_lo, self.escape_lo, self.excluded_lo]),
            torch.cat([self.kept_hi, self.outside_hi, self.escape_hi, self.excluded_hi]),
        )

    def member_boxes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The boxes of the set: kept, then escape (all in ``E``)."""
        return torch.cat([self.kept_lo, self.escape_lo]), torch.cat([self.kept_hi, self.escape_hi])

    def kept_volume_share(self, domain: torch.Tensor) -> float:
        """The kept boxes' share of the state box ``domain`` (the certified set ``S`` in it, less the
        escape set); boxes kept beyond it (``closure_scale``) count only where they meet it."""
        return volume_share(self.kept_lo, self.kept_hi, domain)

    def kept_beyond(self, domain: torch.Tensor) -> int:
        """How many kept boxes lie beyond the state box ``domain`` (a closure over a wider box)."""
        domain = domain.to(self.kept_lo)
        return int(((self.kept_lo < domain[:, 0]) | (self.kept_hi > domain[:, 1])).any(-1).sum())


def volume_share(lo: torch.Tensor, hi: torch.Tensor, domain: torch.Tensor) -> float:
    """The boxes' share of the box ``domain`` (``(n, 2)``): each box counts where it meets it (boxes
    that do not overlap; a closure's wide cover has boxes beyond the state box)."""
    domain = domain.to(lo)
    inside = (torch.minimum(hi, domain[:, 1]) - torch.maximum(lo, domain[:, 0])).clamp(min=0)
    return float((inside / (domain[:, 1] - domain[:, 0])).prod(-1).sum())


class _Grid:
    """The dyadic cell grid of a cover: box corners to integer cell ranges, and covers of boxes.

    Cell edges are the boxes' own corner values (``lo``, ``hi``: every box of the cover), so a
    next-state piece whose bound lies exactly on a box's face is placed in the cell on its side only:
    a face the dynamics leave in place (a heading that the pursuer's turn only matches) does not
    spill into the neighbouring cell. An edge that no box has a corner on separates two cells of the
    same box wherever it runs, so its value (the even division of the span) cannot change an answer."""

    def __init__(
        self, domain: torch.Tensor, resolution: int, lo: torch.Tensor | None = None, hi: torch.Tensor | None = None
    ) -> None:
        self.domain, self.resolution, self.n = domain, resolution, domain.shape[0]
        self.span = domain[:, 1] - domain[:, 0]
        steps = torch.arange(resolution + 1, dtype=torch.float64)
        self.edges = (domain[:, :1] + self.span[:, None] * steps / resolution).cpu()
        self.edges[:, 0], self.edges[:, -1] = domain[:, 0].cpu(), domain[:, 1].cpu()
        if lo is not None and hi is not None and len(lo):
            self._pin(torch.cat([lo, hi]).cpu())

    def _pin(self, corners: torch.Tensor) -> None:
        """Set each edge to the value of the box corners on it; refuse corners that disagree."""
        index, _ = self.cells(corners, corners, exact=True)
        for d in range(self.n):
            low = self.edges[d].scatter_reduce(0, index[:, d], corners[:, d], "amin", include_self=False)
            high = self.edges[d].scatter_reduce(0, index[:, d], corners[:, d], "amax", include_self=False)
            if not torch.equal(low, high):
                raise ValueError("two boxes' corners on one cell edge differ: the boxes do not fit together")
            self.edges[d] = low
            if not bool((self.edges[d][1:] > self.edges[d][:-1]).all()):
                raise ValueError("the boxes' corners are not in the order of the cell grid")

    def cells(self, lo: torch.Tensor, hi: torch.Tensor, exact: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """Cell ranges ``[a, b)`` per dimension: exact corners of grid boxes (``exact``, refused if off
        the grid), or the fewest cells whose closed union holds a box of states."""
        if exact:
            a = (lo - self.domain[:, 0]) / self.span * self.resolution
            b = (hi - self.domain[:, 0]) / self.span * self.resolution
            ra, rb = torch.round(a), torch.round(b)
            if bool(((a - ra).abs() > 1e-6).any() or ((b - rb).abs() > 1e-6).any()):
                raise ValueError("a box's corners are not on the certificate's cell grid")
            return ra.long().clamp(0, self.resolution), rb.long().clamp(0, self.resolution)
        lo, hi = lo.cpu().contiguous(), hi.cpu().contiguous()
        a = torch.stack(
            [torch.searchsorted(self.edges[d], lo[:, d].contiguous(), right=True) for d in range(self.n)], -1
        )
        b = torch.stack([torch.searchsorted(self.edges[d], hi[:, d].contiguous()) for d in range(self.n)], -1)
        a = (a - 1).clamp(0, self.resolution - 1)
        return a, torch.maximum(b, a + 1).clamp(1, self.resolution)

    def cover(self, lo: torch.Tensor, hi: torch.Tensor) -> DyadicCover:
        """The grid boxes ``[lo, hi]`` as a sparse cover of cells."""
        return DyadicCover(*self.cells(lo, hi, exact=True), self.resolution)


def _resolution(result: CertificationResult, domain: torch.Tensor) -> int:
    """The finest grid the cover's boxes sit on: the initial splits times two per halving."""
    span = domain[:, 1] - domain[:, 0]
    smallest = float(((result.hi - result.lo) / span).min())
    return round(1 / smallest) if smallest > 0 else 1


def _next_boxes(verifier: _Verifier, lo: torch.Tensor, hi: torch.Tensor, inputs: torch.Tensor) -> tuple:
    """:meth:`_Verifier.next_boxes`, each with the row of the box it came from."""
    n_lo, n_hi, piece = verifier.next_boxes(lo, hi, inputs)
    return n_lo, n_hi, piece // len(verifier.d_lo)


def _closed(grid: _Grid, cover: DyadicCover, n_lo: torch.Tensor, n_hi: torch.Tensor) -> torch.Tensor:
    """Whether each next-state box lies within the cover's cells."""
    return cover.covers(*grid.cells(n_lo.cpu(), n_hi.cpu(), exact=False))


def _fails(owner: torch.Tensor, hit: torch.Tensor, rows: int) -> torch.Tensor:
    """``(rows,)``: whether any next-state piece of each row hit."""
    fails = torch.zeros(rows, dtype=torch.long)
    fails.scatter_reduce_(0, owner, hit.long(), reduce="amax")
    return fails.bool()


def certified_set(
    value_function: NeuralValueFunction | ValueNetwork, result: CertificationResult, rounds: list | None = None
) -> Certificate:
    """The largest union of ``result``'s boxes that is invariant (module docstring), as a
    :class:`Certificate`.

    Every box of the cover that holds no failure state (``l > 0`` on all of it, by interval bounds) is
    a candidate, whatever the verifier said of it: the set is the union of the kept boxes, so the
    network need not prove anything of a box whose next states land in kept boxes. A next state may
    also land in a box proven outside ``S_c`` where the network proves ``V >= c`` on it (then it is
    not in that box). Boxes drop out in rounds, and each round checks the survivors against only the
    boxes dropped in the round before (the rest they already passed). A box about to drop first tries
    the other candidate inputs; one whose next states meet no dropped box becomes its backup input,
    and the box stays.

    With an escape set ``E`` (``escape_margin``), next states in ``E`` need no box, and the set is
    ``(kept boxes) ∪ E``. ``E`` holds only while every box meeting the band below it is kept; where
    one is not (from the start, or once it drops), the closure is computed again without ``E`` and
    the certificate is written without it.

    ``rounds``, a list, receives one dict a round: the boxes ``dropped`` and ``switched`` (to another
    input), the share of the state box still ``kept``, and whether ``E`` was assumed (``escape``)."""
    network = _network(value_function)
    verifier = _Verifier(network, result.settings, torch.device("cpu"), closure=True)
    result, grid = _closure_cover(result, verifier)
    (rows, inputs), with_escape = _closure(verifier, grid, result, rounds, None, False)
    finest = (result.hi - result.lo).amin(0)
    for _ in range(result.settings.closure_refinements):
        finest = finest / 2
        result, stay, parts = _split_at_edge(result, rows, inputs, verifier, grid, finest)
        if not bool(parts.any()):
            break
        grid = _Grid(verifier.domain, _resolution(result, verifier.domain), result.lo, result.hi)
        (rows, inputs), with_escape = _closure(verifier, grid, result, rounds, (stay, parts), with_escape)
    settings = result.settings if with_escape else replace(result.settings, escape_margin=None)
    kept = torch.zeros_like(result.status, dtype=torch.bool)
    kept[rows] = True
    escape = (result.status == ESCAPE) & with_escape & ~kept
    outside = (result.status == OUTSIDE) & ~kept
    excluded = ~kept & ~outside & ~escape
    if not with_escape:  # the rest of the partition only matters to the band's check
        excluded[:] = False
    return Certificate(
        settings,
        network.system.config(),
        network_digest(network),
        result.lo[rows],
        result.hi[rows],
        result.candidates[inputs],
        result.lo[outside],
        result.hi[outside],
        grid.resolution,
        result.lo[escape],
        result.hi[escape],
        result.lo[excluded],
        result.hi[excluded],
    )


def _closure(
    verifier: _Verifier,
    grid: _Grid,
    result: CertificationResult,
    rounds: list | None,
    refined: tuple[torch.Tensor, torch.Tensor] | None,
    held: bool,
) -> tuple[tuple[torch.Tensor, torch.Tensor], bool]:
    """:func:`_close` with the escape set assumed where the verifier has one, and without it where a
    box of the band below it drops: ``((rows kept, their input indices), whether E held)``. After a
    refinement, ``refined`` is ``(stay, parts)`` (:func:`_split_at_edge`); ``held``: the boxes that
    stay were kept with ``E``, which holds again (its band's boxes all stay)."""
    if verifier.escape is not None:
        band = verifier.in_band(result.lo, result.hi) & (result.status != ESCAPE)
        closed = _close(verifier, grid, result, rounds, band, refined)
        if closed is not None:
            return closed, True
    if held:  # the boxes that stay lean on E: without it they would need asking again
        raise AssertionError("the escape set held before a refinement and not after it")
    closed = _close(verifier, grid, result, rounds, None, refined)
    assert closed is not None  # without E, the closure always ends
    return closed, False


def _split_at_edge(
    result: CertificationResult,
    rows: torch.Tensor,
    inputs: torch.Tensor,
    verifier: _Verifier,
    grid: _Grid,
    finest: torch.Tensor,
) -> tuple[CertificationResult, torch.Tensor, torch.Tensor]:
    """``result`` with the boxes not kept near the kept set cut into halves along every dimension
    (``CertifySettings.closure_refinements``), which boxes ``stay`` (the kept ``rows``), and which
    are the new ``parts``.

    Cut are the boxes not kept whose parts may be kept (``l > 0`` somewhere on them; not in ``E``,
    not proven outside ``S_c``) that lie within ``closure_refine_reach`` of their own widths of a
    kept box (in every dimension, looked up on a grid of at most ``2**24`` cells; the seam of a
    periodic dimension is not looked across) and are at least twice ``finest`` wide. The parts are
    unknown, each a candidate with its box's backup input to try first. The kept boxes stay whole
    with their ``inputs`` (indices into the candidates): their next states landed in kept boxes,
    which the parts do not change, so the next closure keeps them without asking again, and keeps
    at least what this one did. Only the parts are candidates besides: a box dropped and not cut
    stays out (a smaller set of candidates still closes soundly, and the next closure then costs
    what its parts do, not the whole cover)."""
    kept = torch.zeros(len(result.lo), dtype=torch.bool)
    kept[rows] = True
    backup = result.backup.clone()
    backup[rows] = inputs
    a, b = grid.cells(result.lo, result.hi, exact=True)
    reach = result.settings.closure_refine_reach
    # "near" is looked up on a coarser grid (at most 2**24 cells) where the grid is finer: it only
    # chooses what to cut, so a coarser answer (a little farther) costs time, never soundness
    shift = max(0, math.ceil(math.log2(grid.resolution)) - 24 // grid.n)
    coarse = ((grid.resolution - 1) >> shift) + 1
    near_a = (a - reach * (b - a)).clamp(min=0) >> shift
    near_b = (((b + reach * (b - a)).clamp(max=grid.resolution) - 1) >> shift) + 1
    grown = cover_of(a[kept] >> shift, ((b[kept] - 1) >> shift) + 1, coarse).meets(near_a, near_b)
    may = margin_bounds(verifier.system, result.lo, result.hi).hi > 0  # some part may hold no failure state
    wide = ((result.hi - result.lo) >= 2 * finest * (1 - 1e-9)).all(-1)
    cut = grown & may & ~kept & wide & (result.status != ESCAPE) & (result.status != OUTSIDE)
    lo, hi = result.lo[cut], result.hi[cut]
    mid = (lo + hi) / 2
    corners = torch.tensor(list(itertools.product((0, 1), repeat=lo.shape[-1])), dtype=torch.bool)
    part_lo = torch.where(corners, mid[:, None], lo[:, None]).reshape(-1, lo.shape[-1])
    part_hi = torch.where(corners, hi[:, None], mid[:, None]).reshape(-1, lo.shape[-1])
    parts = len(part_lo)
    status = torch.full((parts,), UNKNOWN, dtype=result.status.dtype)
    refined = replace(
        result,
        lo=torch.cat([result.lo[~cut], part_lo]),
        hi=torch.cat([result.hi[~cut], part_hi]),
        status=torch.cat([result.status[~cut], status]),
        backup=torch.cat([backup[~cut], backup[cut].repeat_interleave(len(corners))]),
    )
    fresh = torch.zeros(parts, dtype=torch.bool)
    return (
        refined,
        torch.cat([kept[~cut], fresh]),
        torch.cat([torch.zeros(int((~cut).sum()), dtype=torch.bool), ~fresh]),
    )


def _closure_cover(result: CertificationResult, verifier: _Verifier) -> tuple[CertificationResult, _Grid]:
    """The cover the closure runs on (``result``'s boxes cut to ``closure_relative_width``, widened by
    ``closure_scale``) and its cell grid, for a closure ``verifier`` (``closure=True``)."""
    result = _widened(_refined(result, verifier.network_domain), verifier)
    return result, _Grid(verifier.domain, _resolution(result, verifier.domain), result.lo, result.hi)


def _refined(result: CertificationResult, domain: torch.Tensor) -> CertificationResult:
    """``result`` with every box wider than ``closure_relative_width`` of the span (escape boxes
    aside) cut into halves down to it. A part keeps its box's backup input as the first one to try,
    but not its status: the bounds of a part are not those the verifier computed (and the checker
    recomputes), so a part counts as unknown, a candidate wherever ``l > 0`` on it."""
    width = result.settings.closure_relative_width
    if width is None:
        return result
    span = domain[:, 1] - domain[:, 0]
    lo, hi, status, backup = result.lo, result.hi, result.status, result.backup
    for d in range(len(span)):
        while True:
            wide = ((hi[:, d] - lo[:, d]) / span[d] > width * (1 + 1e-9)) & (status != ESCAPE)
            if not bool(wide.any()):
                break
            mid = (lo[wide, d] + hi[wide, d]) / 2
            upper_lo, lower_hi = lo[wide].clone(), hi[wide].clone()
            upper_lo[:, d], lower_hi[:, d] = mid, mid
            lo, hi = torch.cat([lo[~wide], lo[wide], upper_lo]), torch.cat([hi[~wide], lower_hi, hi[wide]])
            cut = torch.full_like(status[wide], UNKNOWN)
            status = torch.cat([status[~wide], cut, cut])
            backup = torch.cat([backup[~wide], backup[wide], backup[wide]])
    return replace(result, lo=lo, hi=hi, status=status, backup=backup)


def _widened(result: CertificationResult, verifier: _Verifier) -> CertificationResult:
    """``result``'s cover of the network's box (already cut to ``closure_relative_width``) with the
    rest of the closure's wider box (``closure_scale``) added as cells that wide: unknown, or escape
    where all in ``E``. Their edges continue the cover's own corner values, so the boxes fit."""
    if result.settings.closure_scale == 1:
        return result
    inner = verifier.network_domain.cpu()
    width = result.settings.closure_relative_width * (inner[:, 1] - inner[:, 0])
    edges, inside = [], []
    for d in range(len(inner)):
        corners = torch.unique(torch.cat([result.lo[:, d], result.hi[:, d]]))
        steps = (corners - inner[d, 0]) / width[d]
        corners = corners[(steps - torch.round(steps)).abs() < 1e-6]  # the cover's own floats on the cell grid
        if d in verifier.periodic_dims:
            edges.append(corners)
            inside.append(torch.ones(len(corners) - 1, dtype=torch.bool))
            continue
        more = round(float((verifier.domain[d, 1].cpu() - inner[d, 1]) / width[d]))
        k = torch.arange(1, more + 1, dtype=torch.float64)
        axis = torch.cat([(inner[d, 0] - k * width[d]).flip(0), corners, inner[d, 1] + k * width[d]])
        axis[0], axis[-1] = verifier.domain[d, 0].cpu(), verifier.domain[d, 1].cpu()
        edges.append(axis)
        inside.append(torch.cat([torch.zeros(more), torch.ones(len(corners) - 1), torch.zeros(more)]).bool())
    index = torch.cartesian_prod(*[torch.arange(len(e) - 1) for e in edges]).reshape(-1, len(edges))
    beyond = ~torch.stack([inside[d][index[:, d]] for d in range(len(edges))], -1).all(-1)
    index = index[beyond]
    lo = torch.stack([edges[d][index[:, d]] for d in range(len(edges))], -1)
    hi = torch.stack([edges[d][index[:, d] + 1] for d in range(len(edges))], -1)
    status = torch.where(verifier.in_escape(lo, hi), torch.tensor(ESCAPE), torch.tensor(UNKNOWN))
    return replace(
        result,
        lo=torch.cat([result.lo, lo]),
        hi=torch.cat([result.hi, hi]),
        status=torch.cat([result.status, status]),
        backup=torch.cat([result.backup, torch.full((len(lo),), -1, dtype=torch.long)]),
    )


def _close(
    verifier: _Verifier,
    grid: _Grid,
    result: CertificationResult,
    rounds: list | None,
    band: torch.Tensor | None,
    refined: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The closure's rounds (:func:`certified_set`): ``(rows of result kept, their input indices)``.
    ``band`` given: ``E`` is assumed, and ``None`` is returned once a box of the band drops. Without
    it, a next state that is in ``E`` only (beyond the domain) counts as leaving the set. ``refined``: ``(stay,
    parts)`` after a refinement: boxes known to stay with their ``backup`` input (the kept set before
    it, whose next states all land in it), kept without being asked again, and the only other
    candidates."""
    escape = band is not None
    status, candidates = result.status, result.candidates
    outside = status == OUTSIDE
    # every box that holds no failure state may be kept, whatever the network says of it
    candidate = margin_bounds(verifier.system, result.lo, result.hi).lo > 0
    if escape:
        if bool((band & ~candidate).any()):
            return None  # a box of the band may hold a failure state: E does not hold
        candidate &= status != ESCAPE  # E's boxes are in the set already
    stay = torch.zeros(len(status), dtype=torch.bool)
    if refined is not None:
        stay, parts = refined
        candidate &= parts
    if escape and bool((band & ~candidate & ~stay).any()):
        return None  # a box of the band can no longer be kept (dropped before, and not cut): E does not hold
    fixed = stay.nonzero().squeeze(-1)
    fixed_share = float(((result.hi[fixed] - result.lo[fixed]) / grid.span).prod(-1).sum())
    rows = candidate.nonzero().squeeze(-1)
    lo, hi = result.lo[rows], result.hi[rows]
    in_band = band[rows] if escape else torch.zeros(len(rows), dtype=torch.bool)
    backup = result.backup[rows]
    choice = backup.clamp(min=0)
    # where the verifier proved the backup input's next states to have V >= c
    proven_value = (status[rows] == PROVEN) & (backup >= 0)
    tried = torch.zeros(len(rows), len(candidates), dtype=torch.bool)
    tried[torch.arange(len(rows)), choice] = True
    member = torch.zeros(len(status), dtype=torch.bool)  # the boxes of the set as it stands
    member[rows] = True
    member |= stay
    if escape:
        member |= status == ESCAPE
    boxes = owner_of(*grid.cells(result.lo, result.hi, exact=True), grid.resolution)

    def pieces(at: torch.Tensor, inputs: torch.Tensor) -> _Pieces:
        """The next-state pieces of boxes ``at`` (:class:`_Pieces`): ``free``: all in ``E`` (no cell
        needed); ``bad``: leaves the set whatever the cells (beyond the domain, ``E`` not assumed)."""
        n_lo, n_hi, piece, escaped, needs = verifier.landing(lo[at], hi[at], inputs)
        free = escaped & escape
        bad = ~free & ((needs & (not escape)) | ~verifier.in_domain(n_lo, n_hi))
        ask = (~free & ~bad).nonzero().squeeze(-1)
        n_a, n_b = grid.cells(n_lo[ask].cpu(), n_hi[ask].cpu(), exact=False)
        pair_piece, pair_box = _boxes_met(boxes, n_a, n_b)
        owner = at[piece // len(verifier.d_lo)]
        return _Pieces(owner, version[owner] + 1, free, bad, ask[pair_piece], pair_box)

    def stays(chunks: list[_Pieces], value_ok: torch.Tensor) -> torch.Tensor:
        """Per row: whether every piece of its input lands in the set's boxes, or, where the network
        proved ``V >= c`` on the row's next states, in the set's boxes and boxes of ``V < c`` (a cell
        of no box: neither). A piece counts while its ``version`` is its row's."""
        fails = torch.zeros(len(rows), dtype=torch.bool)
        for p in chunks:
            known = p.pair_box >= 0
            box = p.pair_box.clamp(min=0)
            away = ~known | ~member[box]  # a cell not in the set's boxes
            out = _fails(p.pair_piece, away, len(p.owner))
            open_ = _fails(p.pair_piece, away & (~known | ~outside[box]), len(p.owner))
            ok = p.free | (~p.bad & (~out | (value_ok[p.owner] & ~open_)))
            fails |= _fails(p.owner, ~ok & (p.version == version[p.owner]), len(rows))
        return ~fails

    version = torch.full((len(rows),), -1, dtype=torch.long)  # each row's input's pieces: this version
    current = [pieces(torch.arange(len(rows)), candidates[choice])]
    version += 1
    # parts of proven boxes (closure_relative_width) keep their box's input: show its V >= c again
    # where only that lets their next states meet boxes outside S_c
    hint = (~proven_value & (backup >= 0)).nonzero().squeeze(-1)
    everything = torch.ones(len(rows), dtype=torch.bool)
    if len(hint):
        need = hint[~stays(current, proven_value)[hint] & stays(current, everything)[hint]]
        if len(need):
            proven_value[need] = verifier.keeps(lo[need], hi[need], candidates[choice[need]])
    alive = torch.ones(len(rows), dtype=torch.bool)
    while True:
        failing = alive & ~stays(current, proven_value)
        switched = 0
        for k, u in enumerate(candidates):
            ask = (failing & ~tried[:, k]).nonzero().squeeze(-1)
            if not len(ask):
                continue
            tried[ask, k] = True
            new = pieces(ask, u.expand(len(ask), -1))
            version[ask] += 1  # asked with the new pieces alone
            value_ok = torch.zeros(len(rows), dtype=torch.bool)
            clear = stays([new], value_ok)[ask]
            # the network may still show that the pieces meeting boxes outside S_c land in the set
            maybe = ask[~clear & stays([new], everything)[ask]]
            if len(maybe):
                value_ok[maybe] = verifier.keeps(lo[maybe], hi[maybe], u.expand(len(maybe), -1))
                clear = stays([new], value_ok)[ask]
            version[ask[~clear]] -= 1  # the others keep their input and its pieces
            moved = ask[clear]
            if not len(moved):
                continue
            choice[moved], proven_value[moved], failing[moved] = k, value_ok[moved], False
            switched += len(moved)
            current.append(new.select(torch.isin(new.owner, moved)))
        alive &= ~failing
        if rounds is not None:
            share = fixed_share + float(((hi[alive] - lo[alive]) / grid.span).prod(-1).sum())
            rounds.append({"dropped": int(failing.sum()), "switched": switched, "kept": share, "escape": escape})
        if not bool(failing.any()):
            return torch.cat([fixed, rows[alive]]), torch.cat([result.backup[fixed], choice[alive]])
        if bool((failing & in_band).any()):
            return None  # a box of the band below E is lost: E does not hold
        member[rows[failing]] = False
        if sum(len(p.owner) for p in current) > 2 * int(alive.sum()) * len(verifier.d_lo) + (1 << 16):
            current = [_Pieces.join([p.select((p.version == version[p.owner]) & alive[p.owner]) for p in current])]


class _Pieces(NamedTuple):
    """Next-state pieces of the closure's rows: each piece's ``owner`` row, whether it is ``free``
    (all in ``E``) or ``bad`` (leaves the set whatever the boxes), and the boxes the others meet, as
    pairs (``pair_piece``, ``pair_box``; box -1: a cell that no box holds)."""

    owner: torch.Tensor
    version: torch.Tensor
    free: torch.Tensor
    bad: torch.Tensor
    pair_piece: torch.Tensor
    pair_box: torch.Tensor

    def select(self, keep: torch.Tensor) -> _Pieces:
        """The pieces where ``keep`` (a mask over pieces), their pairs renumbered."""
        index = torch.cumsum(keep.long(), 0) - 1
        pairs = keep[self.pair_piece]
        return _Pieces(
            self.owner[keep],
            self.version[keep],
            self.free[keep],
            self.bad[keep],
            index[self.pair_piece[pairs]],
            self.pair_box[pairs],
        )

    @staticmethod
    def join(chunks: list[_Pieces]) -> _Pieces:
        """One :class:`_Pieces` of all of ``chunks``."""
        offsets = torch.cumsum(torch.tensor([0] + [len(p.owner) for p in chunks]), 0)
        return _Pieces(
            *(torch.cat([getattr(p, name) for p in chunks]) for name in ("owner", "version", "free", "bad")),
            torch.cat([p.pair_piece + offsets[i] for i, p in enumerate(chunks)]),
            torch.cat([p.pair_box for p in chunks]),
        )


#: cells enumerated at once when finding the boxes that next-state pieces meet
CELL_CHUNK = 1 << 22


def _boxes_met(
    boxes: DenseOwner | DyadicCover, n_a: torch.Tensor, n_b: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each box that each cell range ``[n_a, n_b)`` meets, once: ``(range, box)`` pairs (box -1 for a
    cell no box holds), from the owner of every cell of the ranges."""
    size = (n_b - n_a).prod(-1)
    pairs_piece, pairs_box = [], []
    start = 0
    while start < len(n_a):
        total = torch.cumsum(size[start:], 0)
        stop = start + max(1, int(torch.searchsorted(total, torch.tensor(CELL_CHUNK), right=True)))
        cells, row = cells_in(n_a[start:stop], n_b[start:stop])
        key = torch.unique((row + start) * (2**31) + (boxes.owner(cells) + 1))
        pairs_piece.append(key // (2**31))
        pairs_box.append(key % (2**31) - 1)
        start = stop
    if not pairs_piece:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long)
    return torch.cat(pairs_piece), torch.cat(pairs_box)


def save_certificate(path: str | Path, certificate: Certificate) -> Path:
    """Write ``certificate`` atomically (``.npz``; arrays and one JSON header, nothing executable)."""
    path = Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"a certificate file ends in .npz, got {str(path)!r}")
    header = {
        "format": FORMAT,
        "settings": asdict(certificate.settings),
        "system": certificate.system,
        "fingerprint": certificate.fingerprint,
        "resolution": certificate.resolution,
    }
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(  # dyadic box corners compress well: an Air3D certificate holds ~1M boxes
            f,
            header=np.array(json.dumps(header)),
            kept_lo=certificate.kept_lo.numpy(),
            kept_hi=certificate.kept_hi.numpy(),
            inputs=certificate.inputs.numpy(),
            outside_lo=certificate.outside_lo.numpy(),
            outside_hi=certificate.outside_hi.numpy(),
            escape_lo=certificate.escape_lo.numpy(),
            escape_hi=certificate.escape_hi.numpy(),
            excluded_lo=certificate.excluded_lo.numpy(),
            excluded_hi=certificate.excluded_hi.numpy(),
        )
    return path


def load_certificate(path: str | Path) -> Certificate:
    """Read a certificate file (no pickles: nothing in it runs); refuses junk naming the problem."""
    try:
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(str(data["header"]))
            arrays = {k: torch.from_numpy(np.array(data[k], dtype=np.float64)) for k in
                      ("kept_lo", "kept_hi", "inputs", "outside_lo", "outside_hi")}  # fmt: skip
            # files without an escape set may lack these (written before there was one)
            arrays |= {k: torch.from_numpy(np.array(data[k], dtype=np.float64)) for k in
                       ("escape_lo", "escape_hi", "excluded_lo", "excluded_hi") if k in data.files}  # fmt: skip
    except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a reach certificate file ({err})") from None
    found = header.get("format") if isinstance(header, dict) else None
    if found != FORMAT:
        raise ValueError(f"{path}: not a reach certificate file (format {found!r})")
    try:
        settings = CertifySettings(**header["settings"])
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: its settings are not a verifier's ({err})") from None
    return Certificate(
        settings,
        header["system"],
        header["fingerprint"],
        arrays["kept_lo"],
        arrays["kept_hi"],
        arrays["inputs"],
        arrays["outside_lo"],
        arrays["outside_hi"],
        int(header["resolution"]),
        arrays.get("escape_lo"),
        arrays.get("escape_hi"),
        arrays.get("excluded_lo"),
        arrays.get("excluded_hi"),
    )


def check_certificate(
    path: str | Path, value_function: NeuralValueFunction | ValueNetwork, device: str | torch.device = "cpu"
) -> Certificate:
    """Re-verify a certificate file for ``value_function`` from the file alone (module docstring),
    bounding the network on ``device``. Raises ``ValueError`` naming the first thing that does not
    hold; returns the certificate."""
    certificate = load_certificate(path)
    verify_certificate(certificate, value_function, str(path), device)
    return certificate


#: boxes whose value bounds the checker computes at once (its memory grows with the network's width)
CHECK_CHUNK = 65536


def _value_bounds(verifier: _Verifier, lo: torch.Tensor, hi: torch.Tensor) -> Interval:
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
    if network.system.config() != certificate.system:
        theirs, ours = certificate.system.get("name"), network.system.config()["name"]
        what = f"{theirs}, not {ours}" if theirs != ours else f"{ours} with other parameters ({certificate.system})"
        raise ValueError(f"{path}: certifies {what}")
    digest = network_digest(network)
    if digest != certificate.fingerprint:
        raise ValueError(
            f"{path}: certifies the value function {certificate.fingerprint[:12]}..., not this one ({digest[:12]}...): "
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
    network = _network(value_function)
    check_provenance(certificate, network, path)
    settings = certificate.settings
    verifier = _Verifier(network, settings, torch.device("cpu"), closure=True)
    on_device = (
        verifier
        if torch.device(device).type == "cpu"
        else _Verifier(network, settings, torch.device(device), closure=True)
    )
    domain = verifier.domain
    grid = _Grid(domain, certificate.resolution)
    if verifier.escape is None and len(certificate.escape_lo):
        raise ValueError(f"{path}: it has escape boxes but its settings no escape set")
    for name, lo, hi in (("kept", certificate.kept_lo, certificate.kept_hi),
                         ("outside", certificate.outside_lo, certificate.outside_hi),
                         ("escape", certificate.escape_lo, certificate.escape_hi),
                         ("excluded", certificate.excluded_lo, certificate.excluded_hi)):  # fmt: skip
        if lo.ndim != 2 or lo.shape != hi.shape or lo.shape[-1] != domain.shape[0]:
            raise ValueError(f"{path}: its {name} boxes have shape {tuple(lo.shape)}")
        if bool(((lo < domain[:, 0] - 1e-12) | (hi > domain[:, 1] + 1e-12) | (lo > hi)).any()):
            raise ValueError(f"{path}: a {name} box is not a box inside the domain")
        grid.cells(lo, hi, exact=True)
    try:
        grid = _Grid(domain, certificate.resolution, *certificate.every_box())
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    if not bool(verifier.in_network_domain(certificate.outside_lo, certificate.outside_hi).all()):
        raise ValueError(f"{path}: an outside box lies beyond the network's box, where it has no bounds")
    if bool((_value_bounds(on_device, certificate.outside_lo, certificate.outside_hi).hi >= settings.level).any()):
        raise ValueError(f"{path}: an outside box is not proven to hold only V < {settings.level:g}")
    lo, hi, u = certificate.kept_lo, certificate.kept_hi, certificate.inputs
    control = network.system.control_bounds
    low, high = torch.tensor(control.low, dtype=torch.float64), torch.tensor(control.high, dtype=torch.float64)
    if u.shape != (len(lo), len(control.low)) or bool(((u < low) | (u > high)).any()):
        raise ValueError(f"{path}: a backup input is missing or outside the control box")
    margin = margin_bounds(network.system, lo, hi)
    if bool((margin.lo <= 0).any()):
        raise ValueError(f"{path}: a kept box is not proven to keep l(x) > 0")
    if verifier.escape is not None:
        _check_escape(certificate, verifier, grid, path)
    members, allowed = grid.cover(*certificate.member_boxes()), grid.cover(*certificate.allowed_boxes())

    def lower(n_lo: torch.Tensor, n_hi: torch.Tensor) -> torch.Tensor:
        return _value_bounds(on_device, n_lo, n_hi).lo

    land = landing_verdicts(verifier, grid, members, allowed, settings.level, lo, hi, u, lower)
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
    verifier: _Verifier,
    grid: _Grid,
    members: DyadicCover,
    allowed: DyadicCover,
    level: float,
    lo: torch.Tensor,
    hi: torch.Tensor,
    u: torch.Tensor,
    value_lower: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
) -> LandingVerdicts:
    """The certificate's rule for boxes ``[lo, hi]`` under inputs ``u``, piece by piece: one
    implementation for the checker (which names the first condition that fails) and the certified
    filter (point boxes: is the nominal input proven to keep the set?). ``members`` and ``allowed``
    cover the set's boxes and the allowed boxes on ``grid``; ``value_lower`` gives lower bounds of
    ``V`` over next-state boxes, and is asked only about pieces that need it."""
    n_lo, n_hi, piece, escaped, _ = verifier.landing(lo, hi, u)
    count = len(n_lo)
    inside = verifier.in_domain(n_lo, n_hi)
    in_set, in_allowed = torch.zeros(count, dtype=torch.bool), torch.zeros(count, dtype=torch.bool)
    ask = ~escaped & inside
    in_set[ask] = _closed(grid, members, n_lo[ask], n_hi[ask])
    ask &= ~in_set
    in_allowed[ask] = _closed(grid, allowed, n_lo[ask], n_hi[ask])
    in_network = verifier.in_network_domain(n_lo, n_hi)
    value_ok = torch.zeros(count, dtype=torch.bool)
    ask &= in_allowed & in_network
    if bool(ask.any()):
        value_ok[ask] = value_lower(n_lo[ask], n_hi[ask]).cpu() >= level
    return LandingVerdicts(piece, escaped, inside, in_set, in_allowed, in_network, value_ok)


def _check_escape(certificate: Certificate, verifier: _Verifier, grid: _Grid, path: str) -> None:
    """The escape set's own conditions: its boxes lie in ``E``, the file's boxes tile the state box,
    and every box meeting the band below ``E`` is kept (so every state a step from ``E`` may reach
    inside the domain is in the set)."""
    if not bool(verifier.in_escape(certificate.escape_lo, certificate.escape_hi).all()):
        raise ValueError(f"{path}: an escape box is not proven to lie where l >= {verifier.escape[0]:g}")
    every_lo = torch.cat([certificate.kept_lo, certificate.outside_lo, certificate.escape_lo, certificate.excluded_lo])
    every_hi = torch.cat([certificate.kept_hi, certificate.outside_hi, certificate.escape_hi, certificate.excluded_hi])
    a, b = grid.cells(every_lo, every_hi, exact=True)
    whole = torch.zeros(1, grid.n, dtype=torch.long), torch.full((1, grid.n), grid.resolution, dtype=torch.long)
    cells = int((b - a).prod(-1).sum())
    if cells != grid.resolution**grid.n or not bool(DyadicCover(a, b, grid.resolution).covers(*whole).all()):
        raise ValueError(f"{path}: its boxes do not tile the state box (the band below the escape set is unchecked)")
    n_kept = len(certificate.kept_lo)
    band = verifier.in_band(every_lo, every_hi)
    if bool(band[n_kept:].any()):
        raise ValueError(f"{path}: a box meeting the band below the escape set is not kept")
