"""How many torch threads to use: the cores that work of this process's priority or higher leaves free.

torch starts one OpenMP thread per core. When other processes keep those cores busy, its threads
spin-wait on each other, and the run slows by more than the share of the cores it lost (measured:
docs/results/benchmarks.md). The default is therefore the cores other work leaves free, at least one;
``--threads`` or ``OMP_NUM_THREADS`` overrides it.

"Busy" counts only work that competes with this process: on Linux, the threads of other processes
runnable at this moment whose nice value is at most this process's own (a ``nice -n 19`` batch job
yields its core to us, so it does not count) and whose scheduling policy is not ``SCHED_IDLE``; the
median of three reads 10 ms apart. Where the threads' states cannot be read, ``/proc/loadavg``'s
running count (every priority) stands in, and where ``/proc`` is missing, the 1-minute load average,
which lags: it decays with a one-minute time constant, so for over a minute after a job that kept two
cores busy it still rounds to 1 or more.

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


#: ``SCHED_IDLE``: a thread of this policy runs only where nothing else wants the core
_SCHED_IDLE = 5


def _stat_fields(path: str) -> list[str] | None:
    """The fields of a ``/proc/.../stat`` file after the command name (state first), or None where it
    vanished or cannot be read (the command name may hold spaces and parentheses: split after the last)."""
    try:
        with open(path) as fh:
            stat = fh.read()
    except OSError:
        return None
    return stat[stat.rindex(")") + 2 :].split()


def competing_runnable(own_nice: int | None = None) -> int | None:
    """Threads of other processes runnable right now (Linux) that compete with this process: nice value
    at most ``own_nice`` (default: this process's) and a policy other than ``SCHED_IDLE``. None where
    ``/proc`` holds no per-thread states."""
    if own_nice is None:
        own_nice = os.getpriority(os.PRIO_PROCESS, 0)
    own = str(os.getpid())
    try:
        pids = [p for p in os.listdir("/proc") if p.isdigit() and p != own]
    except OSError:
        return None
    count, read_any = 0, False
    for pid in pids:
        try:
            tasks = os.listdir(f"/proc/{pid}/task")
        except OSError:  # the process ended, or is not ours to read
            continue
        for task in tasks:
            fields = _stat_fields(f"/proc/{pid}/task/{task}/stat")
            if fields is None or len(fields) < 39:
                continue
            read_any = True
            count += competes(fields, own_nice)
    return count if read_any else None


def competes(fields: list[str], own_nice: int) -> bool:
    """Whether a thread, given by its ``stat`` fields after the command name, competes for a core with
    work of nice value ``own_nice``: runnable (state ``R``, field 3 of proc(5)), nice (field 19) at most
    ``own_nice``, and not ``SCHED_IDLE`` (policy, field 41)."""
    return fields[0] == "R" and int(fields[16]) <= own_nice and int(fields[38]) != _SCHED_IDLE


def runnable_elsewhere() -> int | None:
    """Threads of other processes runnable right now (Linux) that compete with this one
    (:func:`competing_runnable`); where per-thread states cannot be read, ``/proc/loadavg``'s count of
    running scheduling entities (every priority), less this process's own running threads. None where
    ``/proc`` is missing."""
    try:
        competing = competing_runnable()
    except (OSError, ValueError, IndexError):
        competing = None
    if competing is not None:
        return competing
    try:
        with open("/proc/loadavg") as fh:
            running = int(fh.read().split()[3].split("/")[0])
        own = 0
        for task in os.listdir("/proc/self/task"):
            fields = _stat_fields(f"/proc/self/task/{task}/stat")
            own += fields is not None and fields[0] == "R"
        return max(0, running - own)
    except (OSError, ValueError, IndexError):
        return None


def free_cores() -> int:
    """Cores not taken by other work (at least 1, at most :func:`usable_cores`): those less the threads other
    processes of this process's priority or higher have runnable now (median of three reads, see the module
    docstring), or, where that
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
