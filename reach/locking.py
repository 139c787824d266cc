"""One owner at a time: an exclusive lock on a run directory or a results file, held by a process.

A lock is ``flock`` on a ``.lock`` file. The operating system releases it when its process exits,
however it exits (SIGKILL included), so a killed run never leaves a stale lock behind; the file
records the holder's PID and command line only to name it in the error a second process gets.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import sys
from collections.abc import Iterator
from pathlib import Path


class LockedError(ValueError):
    """Another process holds the lock (its PID and command line are in the message)."""


@contextlib.contextmanager
def exclusive_lock(path: str | os.PathLike, what: str, wait: bool = False) -> Iterator[Path]:
    """Hold an exclusive lock on ``path`` (a lock file, created if needed) for the ``with`` block.

    Args:
        path: the lock file, e.g. ``RUN/.lock`` or ``results.lock``.
        what: what the lock protects, for the error message (``"run directory runs/a"``).
        wait: block until the lock is free instead of raising :class:`LockedError` at once.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = Path(path).read_text(errors="replace").strip() or "another process"
            raise LockedError(f"{what} is in use by {holder}; wait for it to finish or stop it") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"process {os.getpid()} ({' '.join(sys.argv)[:200]})".encode())
        yield path
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def run_lock(run_dir: str | os.PathLike) -> contextlib.AbstractContextManager[Path]:
    """The lock of a run directory (``RUN/.lock``): one process trains or writes a run at a time."""
    return exclusive_lock(Path(run_dir) / ".lock", f"run directory {run_dir}")
