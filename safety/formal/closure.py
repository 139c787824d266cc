"""The closure: a formally certified safe set from the verifier's boxes.

:func:`safety.formal.verifier.certify` proves boxes one at a time: on each **proven** box every state of
``S_c = {V(x, T) >= c}`` is safe and has a backup input that keeps its next state in ``S_c``. Some
boxes stay refuted or unknown, so ``S_c`` itself is not certified. :func:`certified_set` certifies
instead ``S = union of the kept boxes``: every kept box holds no failure state (``l > 0`` on all of
it) and has a backup input under which every next state of the box (every disturbance) lands in a
kept box, or, where the network proves ``V >= c`` on those next states, in a kept box or a box
proven to hold only ``V < c`` (so, in fact, in a kept box). Boxes are dropped until nothing changes
(the largest such union). Then from every state of ``S`` its box's backup input keeps the next state
in ``S``: ``S`` is invariant for all time, and safe. The result is a
:class:`~safety.formal.certificate.Certificate`, which :mod:`safety.formal.checker` re-verifies.

The network's level set guides where the cover is fine and which inputs are tried first; the set
itself is a union of boxes, not ``S_c``. A certificate made when ``S`` was ``S_c ∩ (kept boxes)``
proves the larger union too (its kept boxes' next states were all shown to be in kept boxes with
``V >= c``), so older files check and mean the union.

Closure is checked on the cell grid of the boxes (the verifier's cover is dyadic,
:class:`safety.formal.cover.CellGrid`), held sparsely by :class:`safety.formal.cover.DyadicCover`:
its cost grows with the boxes, not with the ``R**n`` cells, so the 6D and 9D systems' covers are
checked as Air3D's are (grids up to ``2**62`` cells). The closure finds once which boxes each
next-state piece meets (the owner of each of its cells, from a dense table where the grid is small
enough, :class:`safety.formal.cover.DenseOwner`), so that a round costs one pass over those pairs,
whatever the grid. With ``closure_refinements`` the cover then grows finer near the set's edge and
the closure runs again (:func:`_split_at_edge`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from typing import NamedTuple

import torch

from safety.formal.certificate import Boxes, Certificate, Provenance
from safety.formal.cover import CellGrid, boxes_met, cover_of, owner_of
from safety.formal.settings import ESCAPE, OUTSIDE, PROVEN, UNKNOWN, CertificationResult
from safety.formal.verifier import Verifier, margin_bounds, network_of
from training.checkpoint import network_digest
from training.network import NeuralValueFunction, ValueNetwork

__all__ = ["any_by_row", "certified_set", "closure_cover", "closure_rows"]


def _resolution(result: CertificationResult, domain: torch.Tensor) -> int:
    """The finest grid the cover's boxes sit on: the initial splits times two per halving."""
    span = domain[:, 1] - domain[:, 0]
    smallest = float(((result.hi - result.lo) / span).min())
    return round(1 / smallest) if smallest > 0 else 1


def any_by_row(row: torch.Tensor, hit: torch.Tensor, rows: int) -> torch.Tensor:
    """``(rows,)``: whether ``hit`` holds for any entry of each row, ``row`` naming each entry's row
    (which next-state piece of each box, or of each closure row, hit something)."""
    fails = torch.zeros(rows, dtype=torch.long)
    fails.scatter_reduce_(0, row, hit.long(), reduce="amax")
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
    network = network_of(value_function)
    verifier = Verifier(network, result.settings, torch.device("cpu"), closure=True)
    result, grid = closure_cover(result, verifier)
    (rows, inputs), with_escape = _closure(verifier, grid, result, rounds, None, False)
    finest = (result.hi - result.lo).amin(0)
    for _ in range(result.settings.closure_refinements):
        finest = finest / 2
        result, stay, parts = _split_at_edge(result, rows, inputs, verifier, grid, finest)
        if not bool(parts.any()):
            break
        grid = CellGrid(verifier.domain, _resolution(result, verifier.domain), result.lo, result.hi)
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
        Provenance(network.system.config(), network_digest(network)),
        Boxes(result.lo[rows], result.hi[rows]),
        result.candidates[inputs],
        Boxes(result.lo[outside], result.hi[outside]),
        grid.resolution,
        Boxes(result.lo[escape], result.hi[escape]),
        Boxes(result.lo[excluded], result.hi[excluded]),
    )


def _closure(
    verifier: Verifier,
    grid: CellGrid,
    result: CertificationResult,
    rounds: list | None,
    refined: tuple[torch.Tensor, torch.Tensor] | None,
    held: bool,
) -> tuple[tuple[torch.Tensor, torch.Tensor], bool]:
    """:func:`closure_rows` with the escape set assumed where the verifier has one, and without it where a
    box of the band below it drops: ``((rows kept, their input indices), whether E held)``. After a
    refinement, ``refined`` is ``(stay, parts)`` (:func:`_split_at_edge`); ``held``: the boxes that
    stay were kept with ``E``, which holds again (its band's boxes all stay)."""
    if verifier.escape is not None:
        band = verifier.in_band(result.lo, result.hi) & (result.status != ESCAPE)
        closed = closure_rows(verifier, grid, result, rounds, band, refined)
        if closed is not None:
            return closed, True
    if held:  # the boxes that stay lean on E: without it they would need asking again
        raise AssertionError("the escape set held before a refinement and not after it")
    closed = closure_rows(verifier, grid, result, rounds, None, refined)
    assert closed is not None  # without E, the closure always ends
    return closed, False


def _split_at_edge(
    result: CertificationResult,
    rows: torch.Tensor,
    inputs: torch.Tensor,
    verifier: Verifier,
    grid: CellGrid,
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


def closure_cover(result: CertificationResult, verifier: Verifier) -> tuple[CertificationResult, CellGrid]:
    """The cover the closure runs on (``result``'s boxes cut to ``closure_relative_width``, widened by
    ``closure_scale``) and its cell grid, for a closure ``verifier`` (``closure=True``): what
    :func:`certified_set` closes first, and what :func:`closure_rows` takes."""
    result = _widened(_refined(result, verifier.network_domain), verifier)
    return result, CellGrid(verifier.domain, _resolution(result, verifier.domain), result.lo, result.hi)


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


def _widened(result: CertificationResult, verifier: Verifier) -> CertificationResult:
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


def closure_rows(
    verifier: Verifier,
    grid: CellGrid,
    result: CertificationResult,
    rounds: list | None,
    band: torch.Tensor | None,
    refined: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The closure's rounds (:func:`certified_set`) on a cover and its ``grid`` (:func:`closure_cover`):
    ``(rows of result kept, their input indices)``, one dict a round appended to ``rounds`` (a list,
    or ``None``). ``band`` given (a mask over the boxes: those meeting the band below ``E``): ``E`` is
    assumed, and ``None`` is returned once a box of the band drops; an all-false ``band`` assumes
    ``E`` whatever its band does (a diagnostic, not a certificate). Without it, a next state that is
    in ``E`` only (beyond the domain) counts as leaving the set. ``refined``: ``(stay, parts)`` after
    a refinement: boxes known to stay with their ``backup`` input (the kept set before it, whose next
    states all land in it), kept without being asked again, and the only other candidates."""
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
        pair_piece, pair_box = boxes_met(boxes, n_a, n_b)
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
            out = any_by_row(p.pair_piece, away, len(p.owner))
            open_ = any_by_row(p.pair_piece, away & (~known | ~outside[box]), len(p.owner))
            ok = p.free | (~p.bad & (~out | (value_ok[p.owner] & ~open_)))
            fails |= any_by_row(p.owner, ~ok & (p.version == version[p.owner]), len(rows))
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
