"""Boxes on a dyadic cell grid, held sparsely: which cells they cover, at any dimension.

A certificate's boxes (:mod:`safety.formal.certificate`) come from branch and bound: a first cover cut into
halves again and again, so every box's corners are whole cells of a grid of ``R`` cells a dimension,
and each box is a union of aligned cubes of ``2**level`` cells a side. Checking that a next-state box
lies within the certified boxes needs "which boxes does this range of cells meet?". A dense table of
``R**n`` cells answers that only in low dimension (Air3D at 256 cells a dimension: 16M cells; the 9D
system at 8 a dimension already 134M). Here each box is recorded as its aligned cubes at its own
level, and as the (few) larger cubes that contain parts of it at every coarser level, in sorted keys
per level. A query descends from the one cube that holds the whole grid: a cube inside a box
answers at once, a cube no box meets answers at once, and only a cube that boxes meet in part is cut
into its ``2**n`` children. The work grows with the boxes near a query's edge, not with ``R**n``.

The closure asks another question many times over: which box holds each cell a next state meets.
:class:`DenseOwner` answers it from a dense table where the grid is small enough, and
:class:`BrickOwner` where a cover is fine only in places (coarse cells, with dense bricks of cells
where boxes are finer), both by lookups; :func:`owner_of` picks one (the sparse cover's ``owner``
descends, and is the last resort), and :func:`boxes_met` lists the boxes each range of cells meets.
:class:`CellGrid` maps box corners to cells: its edges are the boxes' own corner values.

Sound for any boxes on the grid: "inside a box" is only recorded for a cube that is, and the cells a
query range names are all examined down to single cells where needed. Keys are ``int64``, so the
grid may hold up to ``2**62`` cells (9D at 64 cells a dimension).
"""

from __future__ import annotations

import itertools
import math

import torch

__all__ = [
    "BrickOwner",
    "CellGrid",
    "DenseCover",
    "DenseOwner",
    "DyadicCover",
    "boxes_met",
    "cells_in",
    "cover_of",
    "owner_of",
]

#: the most aligned cubes one box may split into (a branch-and-bound box makes at most 2**n)
MAX_CUBES_PER_BOX = 4096
#: queries answered at once (the frontier of a descent grows with the cubes near each query's edge)
QUERY_CHUNK = 16384


def _trailing_zeros(v: torch.Tensor, cap: int) -> torch.Tensor:
    """How many times 2 divides each entry (``cap`` for 0)."""
    out = torch.full_like(v, cap)
    for level in range(cap - 1, -1, -1):
        out = torch.where((v % (1 << (level + 1))) != 0, torch.full_like(v, level), out)
    return out.clamp(max=cap)


def _cubes(a: torch.Tensor, b: torch.Tensor, level: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The cubes of side ``2**level`` that meet each cell range ``[a, b)``: ``(cube coordinates, row)``."""
    lo = a >> level
    hi = ((b - 1) >> level) + 1
    counts = hi - lo  # (B, n)
    per_box = counts.prod(-1)
    rows = torch.repeat_interleave(torch.arange(len(a)), per_box)
    if not len(rows):
        return torch.empty(0, a.shape[1], dtype=torch.long), rows
    start = torch.cumsum(per_box, 0) - per_box
    rank = torch.arange(len(rows)) - start[rows]  # mixed-radix digits of each cube in its box
    coords = torch.empty(len(rows), a.shape[1], dtype=torch.long)
    for d in range(a.shape[1]):
        coords[:, d] = lo[rows, d] + rank % counts[rows, d]
        rank = rank // counts[rows, d]
    return coords, rows


def _ranges(a: torch.Tensor, b: torch.Tensor, resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell ranges ``[a, b)`` as integers on the CPU, refused unless each is a non-empty range of the
    grid's ``resolution`` cells a dimension."""
    a, b = a.long().cpu(), b.long().cpu()
    if bool(((a < 0) | (b > resolution) | (b <= a)).any()):
        raise ValueError("a box is not a non-empty range of the grid's cells")
    return a, b


def _summed_over_cells(a: torch.Tensor, b: torch.Tensor, resolution: int, weight: torch.Tensor) -> torch.Tensor:
    """``(resolution,) * n``: the sum of ``weight`` (one per box, its dtype the table's) over the boxes
    that hold each cell. Each box adds its weight at its ``2**n`` corners of a difference table with
    alternating signs, and prefix sums along every dimension spread it over its cells."""
    n = a.shape[1]
    table = torch.zeros((resolution + 1,) * n, dtype=weight.dtype)
    for corner in itertools.product((0, 1), repeat=n):
        index = tuple(b[:, d] if up else a[:, d] for d, up in enumerate(corner))
        table.index_put_(index, -weight if sum(corner) % 2 else weight, accumulate=True)
    for d in range(n):
        table = table.cumsum(d)
    return table[(slice(0, resolution),) * n]


def _flat(cells: torch.Tensor, side: int) -> torch.Tensor:
    """Row-major index of each cell of a grid of ``side`` cells a dimension."""
    index = torch.zeros(len(cells), dtype=torch.long)
    for d in range(cells.shape[1]):
        index = index * side + cells[:, d]
    return index


def cells_in(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Every cell of each cell range ``[a, b)`` (``(Q, n)``): ``(cells, row of the range)``."""
    return _cubes(a.long().cpu(), b.long().cpu(), 0)


class DyadicCover:
    """Boxes given as cell ranges ``[a, b)`` (``(B, n)`` integers) on a grid of ``resolution`` cells a
    dimension. :meth:`meets`, :meth:`covers` and :meth:`owner` answer for many queries at once."""

    def __init__(self, a: torch.Tensor, b: torch.Tensor, resolution: int) -> None:
        a, b = _ranges(a, b, resolution)
        n = a.shape[1]
        if n * math.log2(max(resolution, 2)) > 62:
            raise ValueError(f"a grid of {resolution}^{n} cells is too fine for 64-bit cell keys")
        self.n, self.resolution = n, resolution
        self.top = max(0, math.ceil(math.log2(resolution)))
        # each box's own level: the largest cube side its corners are all multiples of
        own = torch.minimum(_trailing_zeros(a, self.top), _trailing_zeros(b, self.top)).amin(-1)
        pieces = ((b - a) >> own.unsqueeze(-1)).prod(-1)
        if bool((pieces > MAX_CUBES_PER_BOX).any()):
            raise ValueError(f"a box splits into more than {MAX_CUBES_PER_BOX} aligned cubes: not a dyadic box")
        self.inside: list[tuple[torch.Tensor, torch.Tensor]] = []  # per level: sorted keys, box of each
        self.met: list[torch.Tensor] = []  # per level: sorted keys of cubes some box meets
        for level in range(self.top + 1):
            mine = (own == level).nonzero().squeeze(-1)
            coords, rows = _cubes(a[mine], b[mine], level)
            keys = self._keys(coords, level)
            order = torch.argsort(keys)
            self.inside.append((keys[order], mine[rows[order]]))
            coarser = (own < level).nonzero().squeeze(-1)
            met, _ = _cubes(a[coarser], b[coarser], level)
            self.met.append(torch.unique(torch.cat([keys, self._keys(met, level)])))

    def _keys(self, coords: torch.Tensor, level: int) -> torch.Tensor:
        return _flat(coords, -(-self.resolution // (1 << level)))  # cubes a dimension at this level

    @staticmethod
    def _find(sorted_keys: torch.Tensor, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Whether each key is among ``sorted_keys``, and where."""
        if not len(sorted_keys):
            return torch.zeros(len(keys), dtype=torch.bool), torch.zeros(len(keys), dtype=torch.long)
        where = torch.searchsorted(sorted_keys, keys).clamp(max=len(sorted_keys) - 1)
        return sorted_keys[where] == keys, where

    def _descend(self, a: torch.Tensor, b: torch.Tensor, want: str) -> torch.Tensor:
        """One traversal for the three questions: ``"meets"`` (any box meets the range), ``"covers"``
        (the boxes cover the range), ``"owner"`` (the box holding a one-cell range, or -1)."""
        a, b = a.long().cpu(), b.long().cpu()
        count = len(a)
        if want == "meets":
            answer = torch.zeros(count, dtype=torch.bool)
        elif want == "covers":
            answer = torch.ones(count, dtype=torch.bool)
        else:
            answer = torch.full((count,), -1, dtype=torch.long)
        query = torch.arange(count)
        cube = torch.zeros(count, self.n, dtype=torch.long)
        for level in range(self.top, -1, -1):
            if not len(query):
                break
            keys = self._keys(cube, level)
            inside_keys, inside_box = self.inside[level]
            inside, where = self._find(inside_keys, keys)
            met, _ = self._find(self.met[level], keys)
            if want == "meets":
                answer[query[inside]] = True
            elif want == "covers":
                answer[query[~met]] = False
            else:
                answer[query[inside]] = inside_box[where[inside]]
            go = met & ~inside
            if want == "meets":
                go &= ~answer[query]
            elif want == "covers":
                go &= answer[query]
            query, cube = query[go], cube[go]
            if level == 0 or not len(query):
                break
            # the children (side 2**(level-1)) that meet the query's range, one dimension at a time
            lo_all, hi_all = a >> (level - 1), (b - 1) >> (level - 1)
            cube = 2 * cube
            for d in range(self.n):
                first = torch.maximum(cube[:, d], lo_all[query, d])
                last = torch.minimum(cube[:, d] + 1, hi_all[query, d])
                count_ = last - first + 1  # 1 or 2 (never 0: the parent meets the range)
                query, cube = query.repeat_interleave(count_), cube.repeat_interleave(count_, 0)
                offset = torch.arange(len(query)) - (torch.cumsum(count_, 0) - count_).repeat_interleave(count_)
                cube[:, d] = first.repeat_interleave(count_) + offset
        return answer

    def _chunked(self, a: torch.Tensor, b: torch.Tensor, want: str) -> torch.Tensor:
        if not len(a):
            return self._descend(a, b, want)
        chunks = range(0, len(a), QUERY_CHUNK)
        return torch.cat([self._descend(a[i : i + QUERY_CHUNK], b[i : i + QUERY_CHUNK], want) for i in chunks])

    def meets(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``(Q,)``: whether any box meets each cell range ``[a, b)`` (``(Q, n)``) in a cell."""
        return self._chunked(a, b, "meets")

    def covers(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``(Q,)``: whether the boxes together cover every cell of each range ``[a, b)``."""
        return self._chunked(a, b, "covers")

    def owner(self, cells: torch.Tensor) -> torch.Tensor:
        """``(Q,)``: the index of a box holding each cell (``(Q, n)``), -1 where none does."""
        return self._chunked(cells, cells + 1, "owner")


#: grids of at most this many cells are answered from a dense table (:class:`DenseCover`)
DENSE_MAX_CELLS = 2**25


class DenseCover:
    """The same boxes as :class:`DyadicCover`, answered from a dense table of the grid's cells: for a
    grid small enough to hold (``resolution**n <= DENSE_MAX_CELLS``, Air3D up to 256 x 256 x 512),
    where :meth:`meets` costs a few lookups per query instead of a descent. Built in ``O(R**n)``:
    each box adds +-1 at its ``2**n`` corners of a difference table, whose prefix sums count the
    boxes over each cell; the prefix sums of "some box here" then answer any range at once."""

    def __init__(self, a: torch.Tensor, b: torch.Tensor, resolution: int) -> None:
        a, b = _ranges(a, b, resolution)
        n = a.shape[1]
        if resolution**n > DENSE_MAX_CELLS:
            raise ValueError(f"a grid of {resolution}^{n} cells is too large for a dense table")
        self.n, self.resolution = n, resolution
        held = (_summed_over_cells(a, b, resolution, torch.ones(len(a), dtype=torch.int64)) > 0).to(torch.int64)
        self._sums = torch.zeros((resolution + 1,) * n, dtype=torch.int64)
        for d in range(n):
            held = held.cumsum(d)
        self._sums[(slice(1, None),) * n] = held

    def _held(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``(Q,)``: how many cells of each range ``[a, b)`` some box holds."""
        a, b = a.long().cpu(), b.long().cpu()
        total = torch.zeros(len(a), dtype=torch.int64)
        for corner in itertools.product((0, 1), repeat=self.n):
            index = tuple(b[:, d] if up else a[:, d] for d, up in enumerate(corner))
            sign = 1 if (self.n - sum(corner)) % 2 == 0 else -1
            total += sign * self._sums[index]
        return total

    def meets(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``(Q,)``: whether any box meets each cell range ``[a, b)`` (``(Q, n)``) in a cell."""
        return self._held(a, b) > 0

    def covers(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``(Q,)``: whether the boxes together cover every cell of each range ``[a, b)``."""
        return self._held(a, b) == (b.long().cpu() - a.long().cpu()).prod(-1)


def cover_of(a: torch.Tensor, b: torch.Tensor, resolution: int) -> DenseCover | DyadicCover:
    """The boxes as a :class:`DenseCover` where the grid is small enough, else a :class:`DyadicCover`
    (both answer :meth:`meets` and :meth:`covers` alike)."""
    n = a.shape[1] if a.ndim == 2 else 1
    return DenseCover(a, b, resolution) if resolution**n <= DENSE_MAX_CELLS else DyadicCover(a, b, resolution)


#: grids of at most this many cells get a dense table of owners (:class:`DenseOwner`, 4 bytes a cell)
DENSE_OWNER_MAX_CELLS = 2**27


class DenseOwner:
    """Which box holds each cell, from a dense table, for boxes that do not overlap (a partition's):
    each box adds its ``index + 1`` at its ``2**n`` corners of a difference table with alternating
    signs, and the prefix sums leave every cell the index of the one box over it (0: none). For
    grids of ``resolution**n <= DENSE_OWNER_MAX_CELLS``; answers :meth:`owner` as
    :meth:`DyadicCover.owner` does, by one lookup. Overlapping boxes are refused."""

    def __init__(self, a: torch.Tensor, b: torch.Tensor, resolution: int) -> None:
        a, b = _ranges(a, b, resolution)
        n = a.shape[1]
        if resolution**n > DENSE_OWNER_MAX_CELLS:
            raise ValueError(f"a grid of {resolution}^{n} cells is too large for a dense table")
        if int((b - a).prod(-1).sum()) > resolution**n:
            raise ValueError("the boxes overlap: a cell has no one owner")
        self.n, self.resolution = n, resolution
        if bool((_summed_over_cells(a, b, resolution, torch.ones(len(a), dtype=torch.int32)) > 1).any()):
            raise ValueError("the boxes overlap: a cell has no one owner")
        ids = torch.arange(1, len(a) + 1, dtype=torch.int64)  # one box over each cell: its sum is its id
        self._owner = (_summed_over_cells(a, b, resolution, ids) - 1).to(torch.int32)

    def owner(self, cells: torch.Tensor) -> torch.Tensor:
        """``(Q,)``: the index of the box holding each cell (``(Q, n)``), -1 where none does."""
        cells = cells.long().cpu()
        return self._owner[tuple(cells.unbind(-1))].long()


#: the coarse table of a :class:`BrickOwner` holds at most this many cells
BRICK_COARSE_MAX_CELLS = 2**24
#: ... and its bricks at most this many cells in all (else :func:`owner_of` descends a sparse cover)
BRICK_FINE_MAX_CELLS = 2**28


class TooFineForBricksError(ValueError):
    """More cells lie in boxes finer than a :class:`BrickOwner`'s coarse cells than its bricks hold."""


class BrickOwner:
    """Which box holds each cell, for boxes that do not overlap, on grids too fine for a dense table:
    a dense table of coarse cells (``2**shift`` cells a side), each naming the box that holds it whole,
    or a **brick**, a dense table of its own cells, where boxes smaller than a coarse cell lie (a
    cover made fine only near a set's edge has few such cells). Two lookups a query, as
    :class:`DenseOwner`; built in time and memory of the coarse cells plus the bricks' cells.
    Overlapping boxes are refused."""

    def __init__(self, a: torch.Tensor, b: torch.Tensor, resolution: int) -> None:
        a, b = _ranges(a, b, resolution)
        n = a.shape[1]
        self.n, self.resolution = n, resolution
        levels = max(0, math.ceil(math.log2(max(resolution, 1))))
        self.shift = max(0, levels - int(math.log2(BRICK_COARSE_MAX_CELLS)) // n)
        self.side = ((resolution - 1) >> self.shift) + 1  # coarse cells a dimension
        unit = 1 << self.shift
        whole = ((a % unit == 0) & ((b % unit == 0) | (b == resolution))).all(-1)  # unions of coarse cells
        coarse_a, coarse_b = a[whole] >> self.shift, ((b[whole] - 1) >> self.shift) + 1
        fine = (~whole).nonzero().squeeze(-1)
        volume = int((b[fine] - a[fine]).prod(-1).sum())
        if volume > BRICK_FINE_MAX_CELLS:
            raise TooFineForBricksError(f"boxes finer than the coarse cells hold {volume} cells: too many for bricks")
        rows = whole.nonzero().squeeze(-1)
        self._coarse = torch.full((self.side**n,), -1, dtype=torch.int32)
        if len(rows):
            table = DenseOwner(coarse_a, coarse_b, self.side)._owner.reshape(-1).long()
            self._coarse = torch.where(table >= 0, rows[table.clamp(min=0)], -1).to(torch.int32)
        cells, row = cells_in(a[fine], b[fine])
        at = _flat(cells >> self.shift, self.side)
        split, brick = torch.unique(at, return_inverse=True)
        if bool((self._coarse[split] >= 0).any()):
            raise ValueError("the boxes overlap: a cell has no one owner")
        self._brick = torch.full((self.side**n,), -1, dtype=torch.long)
        self._brick[split] = torch.arange(len(split))
        slot = brick * unit**n + _flat(cells % unit, unit)
        if len(slot) and int(torch.bincount(slot).max()) > 1:
            raise ValueError("the boxes overlap: a cell has no one owner")
        self._cells = torch.full((len(split) * unit**n,), -1, dtype=torch.int32)
        self._cells[slot] = fine[row].to(torch.int32)

    def owner(self, cells: torch.Tensor) -> torch.Tensor:
        """``(Q,)``: the index of the box holding each cell (``(Q, n)``), -1 where none does."""
        cells = cells.long().cpu()
        at = _flat(cells >> self.shift, self.side)
        brick = self._brick[at]
        unit = 1 << self.shift
        inner = brick.clamp(min=0) * unit**self.n + _flat(cells % unit, unit)
        found = self._cells[inner].long() if len(self._cells) else torch.full_like(at, -1)
        return torch.where(brick >= 0, found, self._coarse[at].long())


def owner_of(a: torch.Tensor, b: torch.Tensor, resolution: int) -> DenseOwner | BrickOwner | DyadicCover:
    """Boxes that do not overlap as a :class:`DenseOwner` where the grid is small enough, else a
    :class:`BrickOwner` where its bricks fit, else a :class:`DyadicCover` (all answer :meth:`owner`)."""
    n = a.shape[1] if a.ndim == 2 else 1
    if resolution**n <= DENSE_OWNER_MAX_CELLS:
        return DenseOwner(a, b, resolution)
    try:
        return BrickOwner(a, b, resolution)
    except TooFineForBricksError:
        return DyadicCover(a, b, resolution)


#: cells enumerated at once when finding the boxes that next-state pieces meet (:func:`boxes_met`)
CELL_CHUNK = 1 << 22


def boxes_met(
    boxes: DenseOwner | BrickOwner | DyadicCover, n_a: torch.Tensor, n_b: torch.Tensor
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


class CellGrid:
    """The cell grid of a cover of boxes, ``resolution`` cells a dimension over ``domain``: box corners
    to integer cell ranges (:meth:`cells`), and covers of boxes (:meth:`cover`). The closure
    (:mod:`safety.formal.closure`), the checker (:mod:`safety.formal.checker`) and the certified
    filter all look boxes up on it.

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
