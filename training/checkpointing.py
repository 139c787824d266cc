"""What a training run saves and takes back up: checkpoints, snapshots, the resumed state, and what a
diverged run kept.

Why a module of its own: :class:`~training.trainer.Trainer` steps, and a :class:`Checkpointer`
turns where it stands (step, wall time, loss average, lower-bound labels) into the run directory's
files (:mod:`training.run_directory`) and back, including the sampling streams of every process of
a distributed run (:mod:`training.distributed`) and the warning when a stream cannot carry over.
"""

from __future__ import annotations

import json
import warnings
from typing import Any

import torch

from training.config import TrainConfig
from training.cuda_graph import portable_state
from training.distributed import Processes
from training.network import ValueNetwork
from training.run_directory import CheckpointState, RunDirectory
from training.sampling import Labels, PointSampler

#: where a run stands, as :meth:`Checkpointer.restore` returns it: step, wall time, loss average, labels
Standing = tuple[int, float, float | None, Labels | None]


class Checkpointer:
    """Saves and restores one run's training state in its directory (rank 0 writes; every process
    of a distributed run takes part in a checkpoint, since rank 0 gathers their streams)."""

    def __init__(
        self,
        run: RunDirectory,
        config: TrainConfig,
        processes: Processes,
        network: ValueNetwork,
        optimizer: torch.optim.Optimizer,
        sampler: PointSampler,
    ) -> None:
        self.run = run
        self.config = config
        self.processes = processes
        self.network = network
        self.optimizer = optimizer
        self.sampler = sampler

    def metadata(self, step: int, wall: float, **fields: Any) -> dict[str, Any]:
        """A checkpoint's or snapshot's metadata: where the run stands, ``fields``, and its configuration."""
        return {
            "steps": step,
            "wall_time_s": wall,
            **fields,
            "seed": self.config.seed,
            "config": json.loads(self.config.to_json()),
        }

    def save(self, step: int, wall: float, loss_ema: float | None, labels: Labels | None) -> None:
        """Checkpoint the run. Every process of a distributed run calls this at the same step: rank 0
        gathers their sampling streams and labels and writes the checkpoint alone."""
        generator = self.sampler.generator
        on_cpu = None if labels is None else tuple(v.cpu() for v in labels)
        streams = self.processes.gather((generator.get_state(), on_cpu))
        if not self.processes.main:
            return
        state = CheckpointState(
            portable_state(self.optimizer.state_dict()),  # loads into an eager or a graphed run alike
            generator.get_state(),
            step,
            wall,
            loss_ema,
            labels,
            streams if len(streams) > 1 else None,
        )
        self.run.save_checkpoint(self.network, state, self.metadata(step, wall))

    def snapshot(self, index: int, step: int, wall: float, fraction: float) -> None:
        """Save the network alone as snapshot ``index`` (of ``config.snapshots``), with its step, wall
        time and progress ``fraction`` (rank 0's part alone in a distributed run)."""
        if not self.processes.main:
            return
        meta = self.metadata(step, wall, fraction=fraction, snapshot=index, snapshots=self.config.snapshots)
        self.run.save_snapshot(index, self.network, meta)

    def restore(self, state: CheckpointState, trained_on: str, device: torch.device) -> Standing:
        """Take up a checkpoint's training state (its weights are loaded already): the optimizer's and
        this process's sampling stream here, and where the run stood, returned. Warns (to the caller
        of :meth:`Trainer.resume <training.trainer.Trainer.resume>`) when the stream cannot carry over."""
        self.optimizer.load_state_dict(state.optimizer)
        step = state.step
        generator, labels = state.stream(self.processes.rank, self.processes.world_size)
        if self.sampler.resume_stream(generator, trained_on, step) and self.processes.main:
            written = len(state.streams or [state.generator])
            if written != self.processes.world_size:  # the streams are per process: they cannot carry over
                why = (
                    f"written by {written} process(es), resumed by {self.processes.world_size} at step {step}: "
                    "each process's sampling generator is reseeded from the run's seed, its rank and the step, "
                    "and lower-bound labels are redrawn"
                )
            else:  # a CPU and a CUDA generator have different states: the stream cannot carry over
                why = (
                    f"trained on {trained_on}, resumed on {device.type} at step {step}: the sampling "
                    "generator is reseeded from the run's seed and step"
                )
            warnings.warn(
                f"{self.run.path}: {why} (same schedule and steps, not the sample stream of an uninterrupted run)",
                stacklevel=3,  # the caller of resume
            )
        # checkpoints load on the CPU; the labels train on the run's device
        labels = None if labels is None else tuple(v.to(device) for v in labels)
        return step, state.wall, state.loss_ema, labels

    def diverged_message(self, loss: float, step: int) -> str:
        """What a run that diverged at ``step`` kept on disk, and what to do next: resume from the last
        checkpoint when there is one, start over (with a lower learning rate) when there is none."""
        saved = self.run.checkpoint_step()
        head = f"loss became {loss} at step {step + 1}"
        if saved is None:
            return (
                f"{head}, before the run saved its first checkpoint, so nothing was kept in {self.run.path}; "
                "start over (for example with a lower --lr)"
            )
        return (
            f"{head}; the last good checkpoint (step {saved}) is kept in {self.run.checkpoint_path}; "
            f"`reach train --resume {self.run.path}` continues from it (the same points follow, so "
            "lower the learning rate in a new run if it diverges again)"
        )
