"""One run trained by several processes with torch's DistributedDataParallel, as ``torchrun`` starts them.

Every process holds a replica of the network and draws its own share of each step's points:
``points / world_size`` from its own generator (:func:`training.sampling.rank_seed`; rank 0 keeps the
run's seed). DistributedDataParallel averages the processes' gradients in the backward pass, so a step
is the step one process would take on all the processes' points together. Beside the gradients, the
processes agree every step on what steers the run: the loss terms (averaged, so the divergence check
and the target-loss rule see one loss), the step's time (rank 0's, so the schedule and a time budget
stay in step) and whether to checkpoint or stop after a signal. Rank 0 alone writes to the run
directory (lock, configuration, metrics, checkpoints, snapshots); its checkpoints hold every
process's sampling stream, so the same number of processes resumes a run exactly, and another
number (one process included) reseeds the streams.

Backends: gloo on the CPU, NCCL on CUDA, where each process takes the GPU of its ``LOCAL_RANK``.
A run of one process, ``Processes()``, runs no collective at all.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TypeVar

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from reach.validation import positive_finite
from training.config import TrainConfig

#: what torchrun sets in every process it starts (``init_process_group``'s ``env://`` reads them)
TORCHRUN_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")

#: the process-group backend for each kind of training device
BACKENDS = {"cpu": "gloo", "cuda": "nccl"}

T = TypeVar("T")


@dataclass(frozen=True)
class Processes:
    """The processes that train one run together, as this process sees them: its ``rank`` among
    ``world_size``, its ``local_rank`` on its node, and the process group's ``backend`` (``None``: a
    run of one process, whose collectives return their input)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None

    @property
    def main(self) -> bool:
        """Whether this process is rank 0, the one that writes the run directory and reports."""
        return self.rank == 0

    def device(self, device: str) -> torch.device:
        """The device this process trains on: ``device``, or in a CUDA process group, its ``LOCAL_RANK``'s GPU."""
        chosen = torch.device(device)
        return torch.device("cuda", self.local_rank) if self.backend and chosen.type == "cuda" else chosen

    def check_shares(self, config: TrainConfig) -> None:
        """Refuse batches that do not split evenly among the processes: DistributedDataParallel averages
        their gradients, which is the gradient of the combined batch only when every share is as large."""
        counts = {"points": config.points}
        if config.lower_bound is not None:
            counts["lower_bound_points"] = config.lower_bound_points
        for name, count in counts.items():
            if count % self.world_size:
                raise ValueError(
                    f"{name} {count} does not split evenly among {self.world_size} processes (each draws an "
                    f"equal share of every step's); give a multiple of {self.world_size}"
                )

    def wrap(self, module: torch.nn.Module) -> torch.nn.Module:
        """``module`` behind DistributedDataParallel (which averages its parameters' gradients over the
        processes in every backward pass), or ``module`` itself in a run of one process. Drop the
        wrapper before leaving the process group (see :meth:`training.Trainer.train`)."""
        if self.backend is None:
            return module
        on_gpu = next(module.parameters()).is_cuda
        return DistributedDataParallel(module, device_ids=[self.local_rank] if on_gpu else None)

    def _reduce(self, values: list[float], op: str) -> list[float]:
        """``values`` combined element by element over the processes (float64) with the reduction ``op``
        (``"SUM"``, ``"MAX"``); ``values`` themselves in a run of one process, which touches no
        ``torch.distributed`` at all."""
        if self.backend is None:
            return values
        device = torch.device("cuda", self.local_rank) if self.backend == "nccl" else torch.device("cpu")
        tensor = torch.tensor(values, dtype=torch.float64, device=device)
        dist.all_reduce(tensor, op=getattr(dist.ReduceOp, op))
        return tensor.tolist()

    def mean(self, values: dict[str, float]) -> dict[str, float]:
        """The processes' mean of each value (the loss terms of one step, with the same keys everywhere)."""
        total = self._reduce(list(values.values()), "SUM")
        return {key: value / self.world_size for key, value in zip(values, total)}

    def from_main(self, value: float) -> float:
        """Rank 0's ``value``, in every process."""
        return self._reduce([value if self.main else 0.0], "SUM")[0]

    def any(self, *flags: bool) -> tuple[bool, ...]:
        """For each flag, whether any process set it."""
        return tuple(bool(flag) for flag in self._reduce([float(flag) for flag in flags], "MAX"))

    def gather(self, value: T) -> list[T]:
        """Every process's ``value`` (picklable, on the CPU), by rank; ``[value]`` in a run of one process."""
        if self.backend is None:
            return [value]
        gathered: list[T] = [value] * self.world_size
        dist.all_gather_object(gathered, value)
        return gathered


def torchrun_environment() -> tuple[int, int, int]:
    """``(rank, world_size, local_rank)`` from the variables torchrun sets; ``ValueError`` naming those
    missing or malformed (checked before anything is built or waited for)."""
    missing = [name for name in TORCHRUN_VARIABLES if not os.environ.get(name, "").strip()]
    if missing:
        raise ValueError(
            f"distributed training runs under torchrun, which sets {', '.join(missing)} (not set here); start it "
            "with `torchrun --nproc-per-node N -m reach train --distributed ...`"
        )
    numbers = {}
    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_PORT"):
        text = os.environ[name].strip()
        if not text.isdigit():
            raise ValueError(f"distributed training: {name}={text!r} is not a non-negative integer")
        numbers[name] = int(text)
    rank, world_size = numbers["RANK"], numbers["WORLD_SIZE"]
    if not rank < world_size:
        raise ValueError(f"distributed training: RANK {rank} is not below WORLD_SIZE {world_size}")
    if not 0 < numbers["MASTER_PORT"] < 65536:
        raise ValueError(f"distributed training: MASTER_PORT {numbers['MASTER_PORT']} is not a TCP port")
    return rank, world_size, numbers["LOCAL_RANK"]


#: seconds a process waits for all of its peers to join before it gives up (``reach train --join-timeout``)
JOIN_TIMEOUT_S = 300.0


@contextlib.contextmanager
def joined(config: TrainConfig, timeout_s: float = JOIN_TIMEOUT_S) -> Iterator[Processes]:
    """Join the process group of the processes torchrun started to train ``config`` (gloo on the CPU,
    NCCL on CUDA) for the ``with`` block, and leave it after. The environment, the device and the
    batch's shares are checked first, so a bad start fails at once in every process instead of
    leaving the others waiting for it. Joining waits at most ``timeout_s`` seconds for every peer
    (torch's own rendezvous timeout), saying on stderr that it waits; then ``ValueError`` says who
    was missing."""
    timeout_s = positive_finite("join timeout (s)", timeout_s)
    rank, world_size, local_rank = torchrun_environment()
    device = torch.device(config.device)
    backend = BACKENDS.get(device.type)
    if backend is None:
        raise ValueError(f"distributed training runs on cpu or cuda, not {config.device!r}")
    if not dist.is_available():
        raise ValueError(f"this torch build ({torch.__version__}) has no torch.distributed")
    Processes(rank, world_size, local_rank).check_shares(config)
    if device.type == "cuda":
        if device.index is not None:
            raise ValueError(
                f"distributed training on CUDA gives each process the GPU of its LOCAL_RANK: give --device cuda, "
                f"not {config.device!r}"
            )
        if local_rank >= torch.cuda.device_count():
            raise ValueError(
                f"LOCAL_RANK {local_rank}: this node has {torch.cuda.device_count()} CUDA device(s); start at most "
                "that many processes per node (torchrun --nproc-per-node)"
            )
        if not dist.is_nccl_available():
            raise ValueError(f"this torch build ({torch.__version__}) has no NCCL for distributed training on CUDA")
        torch.cuda.set_device(local_rank)
    where = f"{os.environ['MASTER_ADDR']}:{os.environ['MASTER_PORT']}"
    print(
        f"rank {rank}: waiting for the {world_size} processes to join at {where} (up to {timeout_s:g} s)",
        file=sys.stderr,
        flush=True,
    )
    try:
        dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout_s))
    except dist.DistError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(
            f"distributed training: rank {rank} waited {timeout_s:g} s at {where} and not all {world_size} processes "
            f"joined ({first}); start every process, or give a longer --join-timeout"
        ) from err
    try:
        yield Processes(rank, world_size, local_rank, backend)
    finally:
        dist.destroy_process_group()
