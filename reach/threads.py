"""How many torch threads to use: the cores other processes leave free.

torch starts one OpenMP thread per core. When other processes keep those cores busy, its threads
spin-wait on each other: on the project's 2-core machine with two other CPU-bound processes, a small
``reach evaluate`` (2,000 9D states) took 19.6-35.0 s with 2 threads against 12.2-14.6 s with 1;
on the idle machine 2 threads were faster (5.5-6.6 s against 6.9-8.4 s). The default is therefore
the cores the 1-minute load average leaves free, at least one; ``--threads`` or ``OMP_NUM_THREADS``
overrides it.

The library's long entry points (:meth:`training.Trainer.train`, :func:`safety.verify.verify`) apply
the same policy for their duration through :func:`thread_policy`, unless the caller chose a count:
``OMP_NUM_THREADS``, or a ``torch.set_num_threads`` to anything other than torch's start-up count.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import torch

#: torch's thread count when reach first imported this module (its start-up count, unless the user
#: set one before importing reach)
_IMPORT_COUNT = torch.get_num_threads()
#: the count :func:`apply_thread_policy` last set (the CLI's decision for the whole command)
_applied: int | None = None


def free_cores() -> int:
    """Cores not taken by other work, by the 1-minute load average (at least 1, at most all)."""
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except (OSError, AttributeError):  # not available on this platform
        return cores
    return max(1, min(cores, cores - round(load)))


def apply_thread_policy(threads: int | None) -> int:
    """Set torch's intra-op threads: ``threads`` if given, else ``OMP_NUM_THREADS`` if set, else
    :func:`free_cores`. Returns the count in use, which :func:`thread_policy` then leaves alone."""
    global _applied
    if threads is None:
        env = os.environ.get("OMP_NUM_THREADS", "").strip()
        if env.isdigit() and int(env) > 0:
            return torch.get_num_threads()  # torch already honours it
        threads = free_cores()
    torch.set_num_threads(threads)
    _applied = threads
    return threads


def _default_counts() -> set[int]:
    """Counts that mean "nobody chose": the cores, and torch's count when this module was imported."""
    return {os.cpu_count() or 1, _IMPORT_COUNT}


@contextmanager
def thread_policy(threads: int | None = None) -> Iterator[int]:
    """Run a block with :func:`apply_thread_policy`'s count and restore the caller's count after.

    ``threads=None`` leaves a count already chosen alone (``OMP_NUM_THREADS`` set, a count set by
    :func:`apply_thread_policy`, e.g. by ``reach --threads``, or torch's count changed from its
    start-up value by the caller), so the policy only replaces torch's blind default."""
    global _applied
    before, applied_before = torch.get_num_threads(), _applied
    chosen = threads is None and (
        os.environ.get("OMP_NUM_THREADS", "").strip() != ""
        or before == _applied
        or before not in _default_counts()
    )
    if chosen:
        yield before
        return
    try:
        yield apply_thread_policy(threads)
    finally:
        torch.set_num_threads(before)
        _applied = applied_before
