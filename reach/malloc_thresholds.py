"""Keep freed memory in the process while eager torch code churns through large temporaries.

An eager grid-solver step allocates and frees hundreds of arrays of the grid's size. glibc's
``malloc`` serves blocks above its mmap threshold (128 KiB at first, self-tuned upward later) with
fresh ``mmap`` pages and gives heap memory back to the OS whenever more than its trim threshold lies
free at the top. Both make the next allocation fault its pages in again, so an eager solve spends
much of its time faulting pages in (measured: docs/results/groundtruth.md, *Eager speed*).

:func:`retained_heap` raises both thresholds for the duration of a block and afterwards leaves them
where glibc's own tuning would end (32 MiB and 64 MiB), giving the rest back with ``malloc_trim``.
Elsewhere (macOS, Windows, musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import platform
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: glibc's largest mmap threshold on 64-bit systems (``DEFAULT_MMAP_THRESHOLD_MAX``); larger values are refused
MMAP_THRESHOLD_MAX = 32 * 2**20
#: the trim threshold glibc's self-tuning reaches with that mmap threshold (twice it)
TRIM_THRESHOLD_AFTER = 2 * MMAP_THRESHOLD_MAX


@cache
def _glibc() -> ctypes.CDLL | None:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
        return libc
    except (OSError, AttributeError):  # pragma: no cover - an unusual libc
        return None


def available() -> bool:
    """Whether this process's allocator can be tuned (glibc on Linux)."""
    return _glibc() is not None


@contextmanager
def retained_heap(working_bytes: int = 0) -> Iterator[bool]:
    """Within the block, serve large blocks from the heap and keep up to ``working_bytes`` free there.

    Yields whether the allocator was tuned. Nesting is harmless: the innermost exit already leaves
    the after-values, which the outer exit sets again.
    """
    libc = _glibc()
    if libc is None:
        yield False
        return
    trim = min(max(int(working_bytes), TRIM_THRESHOLD_AFTER), 2**31 - 1)  # mallopt takes an int
    libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)
    libc.mallopt(M_TRIM_THRESHOLD, trim)
    try:
        yield True
    finally:
        libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_AFTER)
        libc.malloc_trim(0)
