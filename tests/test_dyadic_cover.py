"""The sparse cover of dyadic boxes (safety.formal.cover) answers as a dense table of every cell does."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from safety.formal.cover import BrickOwner, DenseCover, DenseOwner, DyadicCover, cells_in


def _partition(n: int, resolution: int, seed: int, splits: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A branch-and-bound-like partition of the grid: random boxes halved along their widest side."""
    g = torch.Generator().manual_seed(seed)
    boxes = [(torch.zeros(n, dtype=torch.long), torch.full((n,), resolution, dtype=torch.long))]
    for _ in range(splits):
        i = int(torch.randint(len(boxes), (1,), generator=g))
        a, b = boxes[i]
        d = int((b - a).argmax())
        if int(b[d] - a[d]) < 2:
            continue
        mid = (a[d] + b[d]) // 2
        left_b, right_a = b.clone(), a.clone()
        left_b[d], right_a[d] = mid, mid
        boxes[i] = (a, left_b)
        boxes.append((right_a, b))
    return torch.stack([a for a, _ in boxes]), torch.stack([b for _, b in boxes])


def _dense(a: torch.Tensor, b: torch.Tensor, n: int, resolution: int) -> torch.Tensor:
    owner = torch.full((resolution,) * n, -1, dtype=torch.long)
    for i in range(len(a)):
        owner[tuple(slice(int(x), int(y)) for x, y in zip(a[i], b[i]))] = i
    return owner


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 4), st.sampled_from([4, 8, 16, 12]), st.integers(0, 10_000), st.integers(0, 120), st.floats(0, 1))
def test_meets_covers_and_owner_agree_with_a_dense_table(n, resolution, seed, splits, share):
    """The sparse cover and the dense one (:class:`DenseCover`) answer as a table painted box by box."""
    a, b = _partition(n, resolution, seed, splits)
    g = torch.Generator().manual_seed(seed + 1)
    chosen = torch.rand(len(a), generator=g) < share  # a subset of the partition: holes to find
    owner = _dense(a[chosen], b[chosen], n, resolution)
    cover = DyadicCover(a[chosen], b[chosen], resolution) if bool(chosen.any()) else None
    qa = torch.randint(0, resolution, (200, n), generator=g)
    qb = torch.minimum(qa + 1 + torch.randint(0, resolution // 2 + 1, (200, n), generator=g), torch.tensor(resolution))
    if cover is None:
        return
    meets, covers = cover.meets(qa, qb), cover.covers(qa, qb)
    table = DenseCover(a[chosen], b[chosen], resolution)  # the closure's dense twin answers alike
    assert torch.equal(table.meets(qa, qb), meets) and torch.equal(table.covers(qa, qb), covers)
    for q in range(len(qa)):
        cells = owner[tuple(slice(int(x), int(y)) for x, y in zip(qa[q], qb[q]))]
        assert bool(meets[q]) == bool((cells >= 0).any())
        assert bool(covers[q]) == bool((cells >= 0).all())
    cells = torch.randint(0, resolution, (300, n), generator=g)
    index = cover.owner(cells)
    expected = owner[tuple(cells.unbind(-1))]
    assert torch.equal(index, expected)  # both number the chosen boxes in the same order


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 4), st.sampled_from([4, 8, 16, 12]), st.integers(0, 10_000), st.integers(0, 120), st.floats(0, 1))
def test_the_owner_tables_and_the_cells_of_ranges_agree_with_a_painted_table(n, resolution, seed, splits, share):
    """:class:`DenseOwner` and :class:`BrickOwner` (the closure's lookups of which box holds a cell)
    answer as the sparse cover's ``owner`` and a table painted box by box, holes (-1) included;
    :func:`cells_in` lists every cell of each range once."""
    a, b = _partition(n, resolution, seed, splits)
    g = torch.Generator().manual_seed(seed + 1)
    chosen = torch.rand(len(a), generator=g) < share
    if not bool(chosen.any()):
        return
    owner = _dense(a[chosen], b[chosen], n, resolution)
    cells = torch.randint(0, resolution, (300, n), generator=g)
    table = DenseOwner(a[chosen], b[chosen], resolution)
    assert torch.equal(table.owner(cells), owner[tuple(cells.unbind(-1))])
    assert torch.equal(table.owner(cells), DyadicCover(a[chosen], b[chosen], resolution).owner(cells))
    with pytest.MonkeyPatch.context() as patch:  # coarse cells of half the grid a side
        patch.setattr("safety.formal.cover.BRICK_COARSE_MAX_CELLS", 2**n)
        bricks = BrickOwner(a[chosen], b[chosen], resolution)
    assert bricks.shift >= 1 and torch.equal(bricks.owner(cells), table.owner(cells))
    listed, row = cells_in(a, b)
    assert len(listed) == resolution**n  # the partition's boxes hold every cell once
    assert bool(((listed >= a[row]) & (listed < b[row])).all())
    assert len(torch.unique(listed, dim=0)) == resolution**n


def test_the_owner_tables_refuse_overlapping_boxes(monkeypatch):
    with pytest.raises(ValueError, match="overlap"):
        DenseOwner(torch.tensor([[0, 0], [1, 1]]), torch.tensor([[2, 2], [3, 3]]), 4)
    monkeypatch.setattr("safety.formal.cover.BRICK_COARSE_MAX_CELLS", 4)  # coarse cells of 2 x 2
    t = torch.tensor
    with pytest.raises(ValueError, match="overlap"):  # a small box inside a coarse cell a box holds whole
        BrickOwner(t([[0, 0], [1, 1]]), t([[2, 2], [2, 2]]), 4)
    with pytest.raises(ValueError, match="overlap"):  # two small boxes on one cell
        BrickOwner(t([[0, 0], [0, 0]]), t([[1, 1], [1, 1]]), 4)
    with pytest.raises(ValueError, match="non-empty range"):
        DenseOwner(torch.tensor([[2, 0]]), torch.tensor([[2, 4]]), 4)


def test_it_refuses_boxes_it_cannot_hold():
    with pytest.raises(ValueError, match="non-empty range"):
        DyadicCover(torch.tensor([[2, 0]]), torch.tensor([[2, 4]]), 4)
    with pytest.raises(ValueError, match="64-bit"):
        DyadicCover(torch.tensor([[0] * 10]), torch.tensor([[1] * 10]), 128)
    with pytest.raises(ValueError, match="aligned cubes"):
        DyadicCover(torch.tensor([[1, 1]]), torch.tensor([[4096, 4096]]), 4096)


def test_a_nine_dimensional_cover_answers_without_a_dense_table():
    """9D at 64 cells a dimension: 2^54 cells, far beyond any table; a few thousand boxes answer."""
    a, b = _partition(9, 64, 0, 3000)
    keep = torch.arange(len(a)) % 7 != 0
    cover = DyadicCover(a[keep], b[keep], 64)
    assert bool(cover.covers(a[keep], b[keep]).all())
    assert not bool(cover.meets(a[~keep], b[~keep]).any())
    assert torch.equal(cover.owner(a[keep]), torch.arange(int(keep.sum())))
