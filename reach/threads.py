"""How many torch threads to use: the cores other processes leave free.

torch starts one OpenMP thread per core. When other processes keep those cores busy, its threads
spin-wait on each other: on the project's 2-core machine with two other CPU-bound processes, a small
``reach evaluate`` (2,000 9D states) took 19.6-35.0 s with 2 threads against 12.2-14.6 s with 1;
on the idle machine 2 threads were faster (5.5-6.6 s against 6.9-8.4 s). The default is therefore
the cores the 1-minute load average leaves free, at least one; ``--threads`` or ``OMP_NUM_THREADS``
overrides it.
"""

from __future__ import annotations

import os


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
    :func:`free_cores`. Returns the count in use."""
    import torch

    if threads is None:
        env = os.environ.get("OMP_NUM_THREADS", "").strip()
        if env.isdigit() and int(env) > 0:
            return torch.get_num_threads()  # torch already honours it
        threads = free_cores()
    torch.set_num_threads(threads)
    return threads
