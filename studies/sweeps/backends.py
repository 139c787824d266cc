"""Where sweep tasks run: in this process, in local worker processes, or as tasks on a Ray cluster.

Every backend takes the same list of task arguments for :func:`studies.sweeps.task.run_task` and yields
``(task, rows or exception)`` as tasks finish, so the sweep writes its results incrementally and a
failed task is reported without stopping the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
from collections.abc import Iterator, Sequence
from typing import Any

from safety.verification.sharding import as_completed, start_ray
from studies.sweeps.task import run_task

TaskArgs = tuple[str, dict[str, Any], str, int, "str | None", "int | None"]  # run_task's positional arguments
Outcome = tuple[TaskArgs, "list[dict[str, Any]] | BaseException"]


def run_local(tasks: Sequence[TaskArgs], workers: int = 1) -> Iterator[Outcome]:
    """Run tasks here (``workers = 1``) or in ``workers`` fresh processes (spawned: no forked torch state)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1:
        for args in tasks:
            try:
                yield args, run_task(*args)
            except (ValueError, RuntimeError, OSError) as err:
                yield args, err
        return
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(run_task, *args): args for args in tasks}
        for future in cf.as_completed(futures):
            try:
                yield futures[future], future.result()
            except Exception as err:  # a worker's error, re-raised here: report it, keep the others
                yield futures[future], err


def run_ray(tasks: Sequence[TaskArgs], address: str | None = None, cpus_per_task: float = 1.0) -> Iterator[Outcome]:
    """Run every task as a Ray task, on the cluster at ``address`` or on a local Ray instance.

    The sweep directory must be on storage every node sees (workers write the runs there; the
    driver writes the report). A Ray instance this function started is shut down at the end; one it
    connected to is left running.
    """
    ray, started = start_ray(address)
    try:
        remote = ray.remote(num_cpus=cpus_per_task, max_retries=0)(run_task)
        yield from as_completed(ray, {remote.remote(*args): args for args in tasks})
    finally:
        if started:
            ray.shutdown()
