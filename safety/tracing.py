"""One filter implementation, run eagerly or traced into a graph: the checks that switch between the two.

A safety filter refuses what it cannot trust: a non-finite value, gradient or optimal input raises
``ValueError`` instead of passing the nominal input. Eagerly that is a Python ``if`` on a tensor's
value. A traced graph (the exported filter, :mod:`safety.filters.export`) has no Python at run time and no
exceptions, and a trace cannot branch on values it has not seen. So while a trace runs
(:func:`recording_trust`), :func:`refuse_untrusted` records each check as a boolean the graph
outputs, and the torch-free runtime raises on it with the same message's meaning; the
value-dependent shortcuts of the eager path (skipping rows that need no backup input, stopping a
backup rollout once every path is decided) compute every row instead (:func:`tracing`), which
changes the work done, never the decision.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import torch

__all__ = ["TrustLedger", "only_rows", "recording_trust", "refuse_untrusted", "tracing"]


class TrustLedger:
    """Whether any check of a traced call met a value it cannot trust (a 0-d bool tensor, traced)."""

    def __init__(self) -> None:
        self.untrusted: torch.Tensor | None = None
        self.rows: torch.Tensor | None = None  # set by only_rows: the rows whose checks count

    def record(self, untrusted: torch.Tensor) -> None:
        """Add a mask of untrusted entries: the ledger becomes True if any entry is (of the rows
        that count, inside :func:`only_rows`)."""
        if self.rows is not None:
            if untrusted.numel() != self.rows.numel():
                raise ValueError(
                    f"a check of {untrusted.numel()} entries inside only_rows over {self.rows.numel()} rows"
                )
            untrusted = untrusted.reshape(self.rows.shape) & self.rows
        flag = untrusted.any()
        self.untrusted = flag if self.untrusted is None else self.untrusted | flag

    def flag(self, like: torch.Tensor) -> torch.Tensor:
        """The ledger's verdict as a 0-d bool tensor on ``like``'s device (False if nothing was checked)."""
        if self.untrusted is None:
            return torch.zeros((), dtype=torch.bool, device=like.device)
        return self.untrusted


_LEDGER: ContextVar[TrustLedger | None] = ContextVar("reach_trust_ledger", default=None)


@contextmanager
def recording_trust() -> Iterator[TrustLedger]:
    """Within this block checks record into the yielded ledger instead of raising, and the filter
    computes every row (a graph trace; see the module docstring)."""
    ledger = TrustLedger()
    token = _LEDGER.set(ledger)
    try:
        yield ledger
    finally:
        _LEDGER.reset(token)


@contextmanager
def only_rows(rows: torch.Tensor) -> Iterator[None]:
    """Within this block a traced check counts only on ``rows`` (a bool mask, one entry per row the
    checks inside see), as the eager path computes only those rows and so checks only them: a value
    the filter computes but does not use cannot refuse the batch. The graph then reads the block's
    work only where ``rows`` holds, so a compiler may skip it elsewhere (:mod:`reach_runtime.native`
    does, at one state per call). Eagerly (no trace) it does nothing."""
    ledger = _LEDGER.get()
    if ledger is None:
        yield
        return
    outer = ledger.rows
    ledger.rows = rows.reshape(-1) if outer is None else rows.reshape(-1) & outer.reshape(-1)
    try:
        yield
    finally:
        ledger.rows = outer


def tracing() -> bool:
    """Whether a graph trace is running (:func:`recording_trust`): value-dependent shortcuts are off."""
    return _LEDGER.get() is not None


def refuse_untrusted(untrusted: torch.Tensor, message: Callable[[], str]) -> None:
    """Raise ``ValueError(message())`` where any entry of the bool mask ``untrusted`` is True;
    while tracing, record the mask instead (the graph's ``untrusted`` output)."""
    ledger = _LEDGER.get()
    if ledger is not None:
        ledger.record(untrusted)
    elif bool(untrusted.any()):
        raise ValueError(message())
