"""A training run's directory (files, lock, checkpoints, metrics), kept so that a killed run resumes exactly.

A run is a directory::

    RUN/config.json        resolved TrainConfig
    RUN/checkpoint.pt      latest good state (network, optimizer, RNG, step, wall time)
    RUN/checkpoint.json    its metadata (system, layout, width, encoding, steps, versions, ...)
    RUN/metrics.jsonl      one JSON line per logged step (loss terms, lr, steps/s, evaluations)
    RUN/tensorboard/       with ``tensorboard = True``: the same metrics as TensorBoard scalars
    RUN/snapshots/NNN.pt   with ``snapshots = K``: the network after each K-th of the run (+ .json),
                           for accuracy-versus-time studies that evaluate after training

Checkpoint files are replaced atomically; metrics lines are appended and flushed, and on resume any
line past the checkpoint's step (or torn by a kill) is dropped, so a killed run resumes exactly
where its last checkpoint stood and its metrics continue without duplicates.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import torch

from reach.atomic import atomic_path
from reach.json_files import read_json
from reach.locking import run_lock
from reach.validation import check_output_dir
from training.checkpoint import network_from_payload, read_checkpoint, save_checkpoint
from training.config import TrainConfig
from training.network import ValueNetwork
from training.sampling import Labels

#: values for keys that a stored config.json predates: the behaviour such runs were trained with
#: (resuming them must not switch on a later default such as the gradient bound)
LEGACY_DEFAULTS: dict[str, Any] = {"gradient_bound": None, "sincos_radius": 1.0}

#: files whose presence means a directory already holds a run
RUN_FILES = ("config.json", "checkpoint.pt", "metrics.jsonl")

#: what ``resume`` may change: stop rules, logging, the device and whether its step is a CUDA graph;
#: anything else would make the resumed run a different run than its checkpoint and metrics say
RESUME_OVERRIDABLE = frozenset(
    {
        "steps",
        "budget_s",
        "target_loss",
        "device",
        "cuda_graph",
        "log_every",
        "checkpoint_every_s",
        "eval_every_s",
        "tensorboard",
    }
)


def clean_metrics(path: Path, last_step: int) -> None:
    """Keep only whole metric lines up to ``last_step`` (drops a torn tail after a kill)."""
    if not path.exists():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            break
        if row.get("step", math.inf) > last_step:
            break
        kept.append(line)
    with atomic_path(path) as tmp:
        Path(tmp).write_text("".join(f"{line}\n" for line in kept))


@dataclass
class CheckpointState:
    """What a checkpoint holds beside the network's weights: the training state that resuming restores."""

    optimizer: dict[str, Any]
    generator: torch.Tensor  # the sampling generator's state
    step: int
    wall: float  # seconds of training, accumulated across resumes
    loss_ema: float | None
    labels: Labels | None  # the lower-bound term's labelled points (on the CPU once loaded)
    #: a run of several processes (training.distributed): every process's generator state and labels, by
    #: rank (``generator`` and ``labels`` are rank 0's); ``None`` for a run of one process
    streams: list[tuple[torch.Tensor, Labels | None]] | None = None

    def extra(self) -> dict[str, Any]:
        """The checkpoint payload's training-state entries."""
        return {
            "optimizer": self.optimizer,
            "generator": self.generator,
            "step": self.step,
            "wall": self.wall,
            "loss_ema": self.loss_ema,
            "labels": self.labels,
            "streams": self.streams,
        }

    @classmethod
    def from_payload(cls, payload: dict[str, Any]) -> CheckpointState:
        """The state a checkpoint payload holds (checkpoints of runs without labels, or of one process, may
        lack them)."""
        return cls(
            payload["optimizer"],
            payload["generator"],
            payload["step"],
            payload["wall"],
            payload["loss_ema"],
            payload.get("labels"),
            payload.get("streams"),
        )

    def stream(self, rank: int, world_size: int) -> tuple[torch.Tensor | None, Labels | None]:
        """The generator state and labels that process ``rank`` of ``world_size`` continues from: its own
        when the checkpoint was written by as many processes, else none (``(None, None)``: its stream
        is reseeded and its labels redrawn)."""
        streams = self.streams or [(self.generator, self.labels)]
        return streams[rank] if len(streams) == world_size else (None, None)


class MetricsLog:
    """``RUN/metrics.jsonl``, one JSON line per logged step (appended and flushed), and with a TensorBoard
    ``board`` the same numbers as scalars. Closes both when its ``with`` block ends."""

    def __init__(self, file: TextIO, board: Any | None) -> None:
        self._file = file
        self._board = board

    def write(self, row: dict[str, Any]) -> None:
        """Append ``row`` (which has the ``step``) to the metrics and its numbers to TensorBoard."""
        self._file.write(json.dumps(row) + "\n")
        self._file.flush()
        if self._board is not None:
            for key, value in row.items():
                if key != "step" and isinstance(value, (int, float)):
                    self._board.add_scalar(key, value, row["step"])

    def close(self) -> None:
        self._file.close()
        if self._board is not None:
            self._board.close()

    def __enter__(self) -> MetricsLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RunDirectory:
    """The files of the training run in ``path`` (see the module docstring)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)

    @property
    def config_path(self) -> Path:
        return self.path / "config.json"

    @property
    def checkpoint_path(self) -> Path:
        return self.path / "checkpoint.pt"

    @property
    def metrics_path(self) -> Path:
        return self.path / "metrics.jsonl"

    @property
    def snapshot_dir(self) -> Path:
        return self.path / "snapshots"

    def snapshot_path(self, index: int) -> Path:
        return self.snapshot_dir / f"{index:03d}.pt"

    def check_new(self) -> None:
        """Refuse a directory that cannot take a new run: not a directory, or one that holds a run."""
        check_output_dir(self.path, "run")
        existing = [name for name in RUN_FILES if (self.path / name).exists()]
        if existing:
            raise ValueError(
                f"{self.path} already holds a run ({', '.join(existing)}); continue it with "
                f"`reach train --resume {self.path}` (Trainer.resume) or choose another directory"
            )

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Create the directory and hold its lock (a second process gets a ``ValueError`` naming this one)."""
        self.path.mkdir(parents=True, exist_ok=True)
        with run_lock(self.path):
            yield

    # ------------------------------------------------------------------ configuration
    def write_config(self, config: TrainConfig) -> None:
        with atomic_path(self.config_path) as tmp:
            Path(tmp).write_text(config.to_json())

    def resumed_config(self, overrides: dict[str, Any]) -> tuple[TrainConfig, str]:
        """The stored configuration with ``overrides`` (those not ``None``) applied, and the kind of
        device (``"cpu"``, ``"cuda"``) it was trained on. Only :data:`RESUME_OVERRIDABLE` keys may differ
        from the stored ones."""
        if not self.config_path.exists():
            raise ValueError(f"{self.path}: no config.json; not a training run directory")
        data = {**LEGACY_DEFAULTS, **read_json(self.config_path, "a run configuration")}
        given = {k: v for k, v in overrides.items() if v is not None}
        fixed = {k: v for k, v in given.items() if k not in RESUME_OVERRIDABLE and data.get(k) != v}
        if fixed:
            stored = ", ".join(f"{k}={data.get(k)!r}" for k in sorted(fixed))
            raise ValueError(
                f"{self.path} was trained with {stored}; a resumed run keeps its configuration (only "
                f"{', '.join(sorted(RESUME_OVERRIDABLE))} may change): start a new run to change {sorted(fixed)}"
            )
        trained_on = torch.device(str(data.get("device") or "cpu")).type
        data.update(given)
        return TrainConfig.from_dict(data), trained_on

    # ------------------------------------------------------------------ checkpoints and snapshots
    def save_checkpoint(self, network: ValueNetwork, state: CheckpointState, meta: dict[str, Any]) -> None:
        save_checkpoint(self.checkpoint_path, network, state.extra(), meta)

    def load_checkpoint(self, network: ValueNetwork, layout: str) -> CheckpointState:
        """Load the checkpoint's weights into ``network`` (the run's, built from config.json, which the
        checkpoint must match) and return the rest of its state."""
        payload = read_checkpoint(self.checkpoint_path)
        net = network_from_payload(self.checkpoint_path, payload, system=network.system, layout=layout)
        if net.architecture() != network.architecture():
            raise ValueError(
                f"{self.checkpoint_path}: network {net.architecture()} does not match the run's "
                f"config.json, which builds {network.architecture()}"
            )
        network.load_state_dict(net.state_dict())
        return CheckpointState.from_payload(payload)

    def checkpoint_step(self) -> int | None:
        """The step of the checkpoint on disk (``None`` without one)."""
        if not self.checkpoint_path.exists():
            return None
        return read_json(self.checkpoint_path.with_suffix(".json"), "checkpoint metadata").get("steps")

    def save_snapshot(self, index: int, network: ValueNetwork, meta: dict[str, Any]) -> None:
        """Save the network alone as snapshot ``index``."""
        self.snapshot_dir.mkdir(parents=True, exist_ok=True)
        save_checkpoint(self.snapshot_path(index), network, None, meta)

    # ------------------------------------------------------------------ metrics
    def clean_metrics(self, last_step: int) -> None:
        """Drop metric lines past ``last_step`` (the checkpoint's) and a torn tail."""
        clean_metrics(self.metrics_path, last_step)

    def metrics_log(self, step: int, tensorboard: bool) -> MetricsLog:
        """The metrics file opened for appending, with TensorBoard scalars if ``tensorboard``; ``step`` is
        where the run stands (TensorBoard events past it, a killed run's tail, are purged)."""
        board = self._tensorboard(step) if tensorboard else None
        return MetricsLog(open(self.metrics_path, "a"), board)

    def _tensorboard(self, step: int) -> Any:
        """A SummaryWriter for the run, purging events past ``step``."""
        try:
            from torch.utils.tensorboard import SummaryWriter  # lazy: optional extra, loaded only when asked for
        except ImportError as err:
            raise ValueError("TensorBoard logging needs: pip install 'reach[tensorboard]'") from err
        return SummaryWriter(str(self.path / "tensorboard"), purge_step=step + 1 if step else None)
