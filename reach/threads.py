"""How many torch threads to use: the cores other processes leave free.

torch starts one OpenMP thread per core. When other processes keep those cores busy, its threads
spin-wait on each other: on the project's 2-core machine with two other CPU-bound processes, a small
``reach evaluate`` (2,000 9D states) took 19.6-35.0 s with 2 threads against 12.2-14.6 s with 1;
on the idle machine 2 threads were faster (5.5-6.6 s against 6.9-8.4 s). The default is therefore
the cores other processes leave free, at least one; ``--threads`` or ``OMP_NUM_THREADS`` overrides
it. "Busy" is counted now, not averaged: on Linux, the threads runnable at this moment
(``/proc/loadavg``'s running count) less this process's own, the median of three reads 10 ms apart.
The 1-minute load average, used where ``/proc`` is missing, lags: it decays with a one-minute time
constant, so for over a minute after a job on both cores of a 2-core machine it still rounds to 1
or more, and the next command would start on one core of an idle machine.

The library's long entry points (:meth:`training.Trainer.train`, :func:`safety.verification.verify.verify`) apply
the same policy for their duration through :func:`thread_policy`, unless the caller chose a count:
``OMP_NUM_THREADS``, or a ``torch.set_num_threads`` to anything other than torch's start-up count.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch

#: torch's thread count when reach first imported this module (its start-up count, unless the user
#: set one before importing reach)
_IMPORT_COUNT = torch.get_num_threads()
#: the count :func:`apply_thread_policy` last set (the CLI's decision for the whole command)
_applied: int | None = None


#: reads of the runnable count behind one decision, and the pause between them (s)
_READS, _READ_PAUSE = 3, 0.01


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the platform reports one (``taskset``,
    container cpusets), else all of the machine's."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):  # not on this platform
        return os.cpu_count() or 1


def runnable_elsewhere() -> int | None:
    """Threads of other processes runnable right now (Linux): ``/proc/loadavg``'s count of running
    scheduling entities, less this process's own running threads. None where ``/proc`` is missing."""
    try:
        with open("/proc/loadavg") as fh:
            running = int(fh.read().split()[3].split("/")[0])
        own = 0
        for task in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{task}/stat") as fh:
                    stat = fh.read()
            except OSError:  # the thread ended between the listing and the read
                continue
            own += stat[stat.rindex(")") + 2] == "R"  # the state follows the command name
        return max(0, running - own)
    except (OSError, ValueError, IndexError):
        return None


def free_cores() -> int:
    """Cores not taken by other work (at least 1, at most :func:`usable_cores`): those less the threads other
    processes have runnable now (median of three reads, see the module docstring), or, where that
    cannot be read, less the 1-minute load average."""
    cores = usable_cores()
    counts = []
    for i in range(_READS):
        count = runnable_elsewhere()
        if count is None:
            break
        counts.append(count)
        if i < _READS - 1:
            time.sleep(_READ_PAUSE)
    if counts:
        busy = sorted(counts)[len(counts) // 2]
    else:
        try:
            busy = round(os.getloadavg()[0])
        except (OSError, AttributeError):  # not available on this platform
            return cores
    return max(1, min(cores, cores - busy))


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
    return {os.cpu_count() or 1, usable_cores(), _IMPORT_COUNT}


@contextmanager
def thread_policy(threads: int | None = None) -> Iterator[int]:
    """Run a block with :func:`apply_thread_policy`'s count and restore the caller's count after.

    ``threads=None`` leaves a count already chosen alone (``OMP_NUM_THREADS`` set, a count set by
    :func:`apply_thread_policy`, e.g. by ``reach --threads``, or torch's count changed from its
    start-up value by the caller), so the policy only replaces torch's blind default."""
    global _applied
    before, applied_before = torch.get_num_threads(), _applied
    chosen = threads is None and (
        os.environ.get("OMP_NUM_THREADS", "").strip() != "" or before == _applied or before not in _default_counts()
    )
    if chosen:
        yield before
        return
    try:
        yield apply_thread_policy(threads)
    finally:
        torch.set_num_threads(before)
        _applied = applied_before
