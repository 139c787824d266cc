"""Deferred SIGINT and SIGTERM: a training loop stops at the end of its step, so it can checkpoint first.

A signal that killed the process mid-step would lose everything since the last checkpoint; caught
here, it only sets a flag that the loop reads between steps (see :meth:`training.Trainer.train`).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any


@contextlib.contextmanager
def deferred_signals() -> Iterator[dict[str, int]]:
    """Catch SIGINT and SIGTERM for the ``with`` block: the yielded dict gets ``{"signal": n}`` and
    the loop stops at the end of its step. A second signal of the same kind acts as usual (a user who
    presses Ctrl-C twice means it). Only the main thread can install handlers; elsewhere this is a no-op."""
    stop: dict[str, int] = {}
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum: int, frame: Any) -> None:
        if stop:  # second signal: restore and re-deliver
            signal.signal(signum, previous[signum])
            signal.raise_signal(signum)
            return
        stop["signal"] = signum

    for sig in previous:
        signal.signal(sig, handler)
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def caught_signal_name(stop: dict[str, int]) -> str:
    """The name (``"SIGINT"``, ``"SIGTERM"``) of the signal that :func:`deferred_signals` caught."""
    return signal.Signals(stop["signal"]).name
