"""safety.tracing: a traced check records instead of raising, and inside only_rows it counts only on
the rows given (as the eager path, which computes only those rows, checks only them)."""

from __future__ import annotations

import pytest
import torch

from safety.tracing import only_rows, recording_trust, refuse_untrusted


def test_a_traced_check_counts_only_on_the_rows_given():
    rows = torch.tensor([True, False, True])
    with recording_trust() as ledger:
        with only_rows(rows):
            refuse_untrusted(torch.tensor([False, True, False]), lambda: "never raised")
        assert not bool(ledger.flag(rows))  # the untrusted entry is on a row that does not count
        with only_rows(rows):
            refuse_untrusted(torch.tensor([[False], [False], [True]]), lambda: "never raised")  # any shape of 3
        assert bool(ledger.flag(rows))
        with only_rows(rows), pytest.raises(ValueError, match="a check of 2 entries inside only_rows over 3 rows"):
            refuse_untrusted(torch.tensor([True, True]), lambda: "never raised")
        assert ledger.rows is None  # restored after the block


def test_eagerly_only_rows_changes_nothing():
    with only_rows(torch.tensor([False])), pytest.raises(ValueError, match="bad row"):
        refuse_untrusted(torch.tensor([True]), lambda: "bad row")
