"""Verification sharded over Ray: the blocks of a verification's rollouts as Ray tasks.

A verification rolls out its states in blocks of ``chunk_size`` (:mod:`safety.verification.rollout_store`). With a
:class:`RayBlocks` backend those blocks run as Ray tasks, on a local Ray instance or the cluster at
``address``, the engine the sweeps already use (:mod:`studies.sweeps.backends`):

- each block is the same states the single process would roll out in that block, so the outcomes
  are identical, bit for bit, where the workers compute as this process does (same CPU kind and
  torch threads: a task takes ``cpus_per_task`` cores and torch as many threads; tested on a local
  Ray instance);
- the value function is put in Ray's object store once and shared by every task;
- a worker lost mid-block (killed, a node gone) has its block re-run by Ray (``max_retries``); an
  exception in a block stops the verification with that error;
- through a :class:`~safety.verification.rollout_store.RolloutStore` (``reach evaluate``) each block is saved by
  this process as it arrives, so an interrupted sharded run resumes with what was done, and no row
  is written until every block is in.

``reach evaluate ... --backend ray [--address ADDR]``; ``verify(..., backend=RayBlocks())``.
"""

from __future__ import annotations

import importlib.util
import socket
from collections.abc import Iterator, Sequence
from typing import Any

import torch

from reach.validation import positive_finite
from reach.value_function import ValueFunction
from safety.verification.rollout import RolloutResult, RolloutSettings, concat_results, rollout

#: the backends ``reach evaluate --backend`` takes
BACKENDS = ("local", "ray")


def _rollout_block(value_function: ValueFunction, states: torch.Tensor, settings: RolloutSettings, run: dict) -> Any:
    return rollout(value_function, states, settings, **run)


#: seconds to wait for a Ray cluster's address to accept a connection before refusing it
CONNECT_TIMEOUT_S = 5.0
#: what ``ray.init(address=...)`` takes besides ``HOST:PORT``: the cluster on this machine, found by Ray
RAY_ADDRESS_WORDS = ("auto", "local")


def check_ray_ready(address: str | None = None, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """Refuse, in one line and before any work, what would make Ray fail late: Ray not installed, an
    address that is not ``HOST:PORT`` (optionally ``ray://HOST:PORT``, or ``auto``/``local``), or one
    where nothing accepts a TCP connection within ``timeout`` seconds (Ray itself retries an
    unreachable address for minutes)."""
    if importlib.util.find_spec("ray") is None:
        raise ValueError("the ray backend needs Ray: pip install 'reach-hj[ray]'")
    if address is None or address in RAY_ADDRESS_WORDS:
        return
    text = address.removeprefix("ray://")
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--address {address!r} is not HOST:PORT (or ray://HOST:PORT, auto, local)")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            pass
    except OSError as err:
        raise ValueError(
            f"--address {address}: no Ray cluster answers there within {timeout:g} s ({err.strerror or err})"
        ) from err


def start_ray(address: str | None = None) -> tuple[Any, bool]:
    """``(ray, started)``: Ray, connected to the cluster at ``address`` or to a local instance (started
    here where none runs, without a dashboard); ``started`` says whether the caller should shut it
    down. ``ValueError`` where Ray is not installed. The sweeps' Ray backend starts Ray the same way."""
    check_ray_ready(address)
    import ray  # lazy: optional extra, only for the Ray backends

    if ray.is_initialized():
        return ray, False
    kwargs: dict[str, Any] = {"address": address} if address else {"include_dashboard": False}
    ray.init(log_to_driver=False, **kwargs)
    return ray, True


def as_completed(ray: Any, pending: dict[Any, Any]) -> Iterator[tuple[Any, Any]]:
    """``(key, result)`` of each Ray task in ``pending`` (object ref -> key) as it finishes; a task
    that raised gives its own exception as the result (Ray's ``RayTaskError`` unwrapped)."""
    pending = dict(pending)
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            key = pending.pop(ref)
            try:
                yield key, ray.get(ref)
            except Exception as err:  # RayTaskError wraps the task's exception: give that one
                cause = getattr(err, "cause", None)
                yield key, cause if isinstance(cause, BaseException) else err


class RayBlocks:
    """Roll out blocks of states as Ray tasks (see the module docstring); a context manager that
    starts a local Ray instance (or connects to ``address``) on entry and shuts down what it started."""

    def __init__(self, address: str | None = None, cpus_per_task: float = 1.0, max_retries: int = 3) -> None:
        self.address = address
        self.cpus_per_task = positive_finite("cpus_per_task", cpus_per_task)
        if isinstance(max_retries, bool) or not isinstance(max_retries, int) or max_retries < 0:
            raise ValueError(f"max_retries must be an integer >= 0, got {max_retries!r}")
        self.max_retries = max_retries
        self._started = False
        self._ray: Any = None

    def __enter__(self) -> RayBlocks:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Start (or connect to) Ray, once; ``ValueError`` if Ray is not installed."""
        if self._ray is None:
            self._ray, self._started = start_ray(self.address)

    def close(self) -> None:
        if self._ray is not None and self._started:
            self._ray.shutdown()
        self._ray, self._started = None, False

    def map(
        self, value_function: ValueFunction, blocks: Sequence[torch.Tensor], settings: RolloutSettings, **run: Any
    ) -> Iterator[tuple[int, RolloutResult]]:
        """``(index, result)`` of each block's rollout, as blocks finish."""
        self.start()
        ray = self._ray
        run = {**run, "progress": False}  # workers print nothing; the driver counts blocks
        task = ray.remote(num_cpus=self.cpus_per_task, max_retries=self.max_retries)(_rollout_block)
        shared = ray.put(value_function)
        pending = {task.remote(shared, block, settings, run): k for k, block in enumerate(blocks)}
        for k, result in as_completed(ray, pending):
            if isinstance(result, BaseException):  # a block failed: the verification stops with its error
                raise result
            yield k, result

    def rollout(
        self, value_function: ValueFunction, states: torch.Tensor, settings: RolloutSettings, **run: Any
    ) -> RolloutResult:
        """The rollout of ``states`` in blocks of ``settings.chunk_size``, the blocks on Ray."""
        size = settings.chunk_size
        blocks = [states[lo : lo + size] for lo in range(0, states.shape[0], size)]
        if not blocks:
            return rollout(value_function, states, settings, **run)
        parts: list[RolloutResult | None] = [None] * len(blocks)
        for k, result in self.map(value_function, blocks, settings, **run):
            parts[k] = result
        return concat_results(parts)


def make_backend(name: str | None, address: str | None = None) -> RayBlocks | None:
    """The block backend ``name`` names: ``None`` or ``"local"`` (this process), ``"ray"``."""
    if name in (None, "local"):
        if address is not None:
            raise ValueError("--address needs --backend ray")
        return None
    if name == "ray":
        check_ray_ready(address)  # a missing Ray or a bad address is bad input, refused before any source
        return RayBlocks(address=address)
    raise ValueError(f"backend must be one of {BACKENDS}, got {name!r}")


__all__ = ["BACKENDS", "CONNECT_TIMEOUT_S", "RayBlocks", "as_completed", "check_ray_ready", "make_backend", "start_ray"]
