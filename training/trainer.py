"""The training loop: Adam steps on fresh points until a stop rule holds, resumable from its checkpoints.

:class:`Trainer` runs one resumable run and leans on one module per other concern: the points each
step draws (:mod:`training.sampling`), the loss (:mod:`training.objective`), the schedule
(:mod:`training.schedule`), what it reports (:mod:`training.progress`), the run's directory with its
lock, checkpoints, metrics and resume state (:mod:`training.run_directory`, whose docstring shows the
layout), what it saves and takes back up (:mod:`training.checkpointing`), Ctrl-C / SIGTERM
(:mod:`training.signals`), and the processes of a distributed run (:mod:`training.distributed`).
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from reach.threads import thread_policy
from training.checkpointing import Checkpointer
from training.config import TrainConfig
from training.cuda_graph import GraphedStep
from training.distributed import Processes
from training.encoding import Encoding
from training.loss import terms_to_floats
from training.network import ValueNetwork
from training.objective import Objective
from training.progress import Evaluator, ProgressReport, StepRecord
from training.run_directory import RunDirectory
from training.sampling import Labels, PointSampler
from training.schedule import Schedule
from training.signals import caught_signal_name, deferred_signals

__all__ = [
    "Trainer",
    "TrainingDivergedError",
    "TrainingInterrupted",
    "build_network",
]


@contextlib.contextmanager
def matmul_precision(precision: str) -> Iterator[None]:
    """Let CUDA float32 matrix products use TF32 tensor cores for a block (``"tf32"``), restoring torch's
    process-wide setting after; ``"float32"`` leaves it alone."""
    before = torch.backends.cuda.matmul.allow_tf32
    if precision == "tf32":
        torch.backends.cuda.matmul.allow_tf32 = True
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32 = before


class TrainingDivergedError(RuntimeError):
    """The loss became NaN or inf; the last good checkpoint, if the run had saved one, is kept (the
    message says which, and ``reach train`` exits with status 3)."""


class TrainingInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM stopped the run; it was checkpointed first, so ``resume`` loses nothing."""


def build_network(config: TrainConfig) -> ValueNetwork:
    """The run's network, initialised from ``config.seed`` alone (not from the global RNG's state, which
    depends on what the process did before: runs of one sweep in one process would differ from the
    same runs in fresh processes)."""
    system = config.build_system()
    value_scale = system.value_scale() if config.value_scale is None else config.value_scale
    encoding = Encoding.for_system(
        system, sincos=config.sincos, value_scale=value_scale, sincos_radius=config.sincos_radius
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        return ValueNetwork(system, config.layout, config.width, config.parameterisation, config.w0, encoding)


class Trainer:
    """Runs one training run in ``run_dir`` (see :mod:`training.run_directory` for its files).

    ``processes`` (from :func:`training.distributed.joined`) makes this process one of several that train
    the run together, each on its share of every step's points; only rank 0 writes to ``run_dir``,
    and its ``evaluator`` alone is used. Without it the run trains in this process alone."""

    def __init__(
        self,
        config: TrainConfig,
        run_dir: str | os.PathLike,
        evaluator: Evaluator | None = None,
        progress: bool = True,
        *,
        processes: Processes | None = None,
        _resuming: bool = False,
    ) -> None:
        self.config = config.validate()
        self.processes = processes or Processes()
        self.processes.check_shares(self.config)
        if self.config.cuda_graph and self.processes.world_size > 1:
            raise ValueError(
                "cuda_graph=True, but this run trains in several processes: DistributedDataParallel's "
                "gradient all-reduce is not captured (leave cuda_graph unset, or false)"
            )
        self.run = RunDirectory(run_dir)
        self.run_dir = self.run.path
        if not _resuming and self.processes.main:  # the others would race rank 0 writing its config
            self.run.check_new()
        if evaluator is not None and getattr(evaluator, "system", None) is not None:
            wanted = config.build_system()
            wanted.require_same_physics(evaluator.system, "the evaluation ground truth")
        self.evaluator = evaluator if self.processes.main else None
        self.progress = progress
        self.device = self.processes.device(config.device)
        self.network = build_network(config).to(self.device)
        self.system = self.network.system
        self.optimizer = torch.optim.Adam(self.network.parameters(), lr=config.lr)
        self.objective = Objective(self.config, self.network)
        #: the objective that steps call: the objective itself, or while a distributed run trains, the
        #: objective behind DistributedDataParallel, which averages the network's gradients over the processes
        self.step_objective: torch.nn.Module = self.objective
        #: the labelled points (x, t, J) of the lower-bound term, refreshed every lower_bound_every steps
        self.labels: Labels | None = None
        self.sampler = PointSampler(
            self.config, self.network, self.device, self.processes.rank, self.processes.world_size
        )
        self.schedule = Schedule(self.config, self.system.horizon)
        #: checkpoints, snapshots and the resumed state (:mod:`training.checkpointing`)
        self.checkpointer = Checkpointer(
            self.run, self.config, self.processes, self.network, self.optimizer, self.sampler
        )
        #: the step as one CUDA graph (training.cuda_graph), built at the first step where the run allows it
        self.graphed: GraphedStep | None = None
        self._wants_graph = self.uses_cuda_graph()  # decided once: the configuration does not change
        self.step = 0
        self.wall = 0.0  # seconds of training, accumulated across resumes
        self.loss_ema: float | None = None

    @property
    def generator(self) -> torch.Generator:
        """The run's sampling generator (its state is checkpointed)."""
        return self.sampler.generator

    @property
    def gradient_bound(self) -> float | None:
        """The gradient bound in the network's normalised coordinates (``gradient_bound`` x l's steepest slope)."""
        return self.objective.settings.gradient_bound

    @property
    def upper_bound(self) -> Any:
        """The pairwise union that bounds the value from above (``None`` without ``config.upper_bound``)."""
        return self.objective.upper_bound

    # ------------------------------------------------------------------ opening and resuming
    @classmethod
    def resume(
        cls,
        run_dir: str | os.PathLike,
        evaluator: Evaluator | None = None,
        progress: bool = True,
        *,
        processes: Processes | None = None,
        **overrides: Any,
    ) -> Trainer:
        """Continue the run in ``run_dir``; ``overrides`` may extend stop rules (steps, budget_s, ...).
        A run trained by any number of processes resumes in one or several (``processes``: every one
        reads ``run_dir``, so on several nodes it must be on storage they all see)."""
        run = RunDirectory(run_dir)
        config, trained_on = run.resumed_config(overrides)
        trainer = cls(config, run.path, evaluator, progress, processes=processes, _resuming=True)
        if run.checkpoint_path.exists():
            state = run.load_checkpoint(trainer.network, config.layout)
            standing = trainer.checkpointer.restore(state, trained_on, trainer.device)
            trainer.step, trainer.wall, trainer.loss_ema, trainer.labels = standing
        if trainer.processes.main:
            run.clean_metrics(trainer.step)
        return trainer

    @classmethod
    def open(cls, config: TrainConfig, run_dir: str | os.PathLike, progress: bool = True) -> Trainer:
        """The run in ``run_dir``: resumed (its stored configuration rules) if it exists, else a new
        run of ``config``. Callers that must not adopt another configuration compare ``.config``."""
        if RunDirectory(run_dir).config_path.exists():
            return cls.resume(run_dir, progress=progress)
        return cls(config, run_dir, progress=progress)

    def needs_training(self) -> bool:
        """Whether :meth:`train` has work left: no stop rule holds yet, or nothing was saved."""
        return self.stop_reason() is None or not self.checkpoint_path.exists()

    # ------------------------------------------------------------------ persistence
    @property
    def checkpoint_path(self) -> Path:
        return self.run.checkpoint_path

    def _save(self) -> None:
        """Checkpoint the run (every process of a distributed run at the same step, :class:`Checkpointer`)."""
        self.checkpointer.save(self.step, self.wall, self.loss_ema, self.labels)

    def _snapshot(self, index: int) -> None:
        """Save the network alone as snapshot ``index`` (:meth:`Checkpointer.snapshot`)."""
        self.checkpointer.snapshot(index, self.step, self.wall, self.progress_fraction())

    def _snapshots_due(self) -> int:
        return self.schedule.snapshots_due(self.progress_fraction())

    # ------------------------------------------------------------------ schedule (see training.schedule)
    def progress_fraction(self) -> float:
        """How far the run is, in [0, 1], by its step or time budget (whichever is further)."""
        return self.schedule.progress(self.step, self.wall)

    def learning_rate(self, frac: float) -> float:
        return self.schedule.learning_rate(frac)

    def time_range(self, frac: float) -> float:
        return self.schedule.time_range(frac)

    def stop_reason(self) -> str | None:
        """Why the run would stop now (a stop rule that holds), or None while it has work left."""
        return self.schedule.stop_reason(self.step, self.wall, self.loss_ema)

    # ------------------------------------------------------------------ one step
    def _sample(self, tmax: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """This step's points and boundary mask (see :meth:`PointSampler.points`)."""
        return self.sampler.points(tmax)

    def _refresh_labels(self, tmax: float) -> None:
        """Label fresh states with what the network's policy achieves (``J <= V``), every
        ``lower_bound_every`` steps (and at the start of a run that has none)."""
        c = self.config
        if c.lower_bound is None or tmax <= 0:
            return
        if self.labels is not None and self.step % c.lower_bound_every:
            return
        self.labels = self.sampler.lower_bound_labels(tmax)

    def _optimise(self) -> StepRecord:
        """One Adam step on fresh points at the schedule's learning rate and time range; its time counts
        toward ``wall``. Raises :class:`TrainingDivergedError` if the loss is not finite.

        In a distributed run the processes' loss terms are averaged before the backward pass (they all
        see the combined batch's loss, so they diverge and meet a target loss together), and the step's
        time is rank 0's (their schedules and time budgets stay in step; the others' steps also hold
        the time they wait while rank 0 checkpoints or evaluates, which is not training)."""
        t0 = time.perf_counter()
        frac = self.progress_fraction()
        lr = self.learning_rate(frac)
        tmax = self.time_range(frac)
        self._refresh_labels(tmax)  # counted as training time: it is part of the recipe's cost
        if self.graphed is None and self._wants_graph:
            self.graphed = GraphedStep(self.sampler, self.objective, self.optimizer)
        if self.graphed is not None:
            if self.sampler.refuted is not None:
                raise ValueError("refuted points train without a CUDA graph (set cuda_graph=False)")
            terms = self.graphed(lr, tmax, self.labels)  # updates first, checks after (training.cuda_graph)
            if not math.isfinite(terms["loss"]):
                raise TrainingDivergedError(self._diverged_message(terms["loss"]))
        else:
            for group in self.optimizer.param_groups:
                group["lr"] = lr
            x, t, mask = self._sample(tmax)
            refuted = self.sampler.refuted_batch(tmax)
            loss, tensors = self.step_objective(x, t, mask, self.schedule.trains_pde(frac), self.labels, refuted)
            terms = self.processes.mean(terms_to_floats(tensors))
            if not math.isfinite(terms["loss"]):
                raise TrainingDivergedError(self._diverged_message(terms["loss"]))
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
        self.step += 1
        self.wall += self.processes.from_main(time.perf_counter() - t0)
        self.loss_ema = terms["loss"] if self.loss_ema is None else 0.95 * self.loss_ema + 0.05 * terms["loss"]
        return StepRecord(lr, tmax, terms)

    def uses_cuda_graph(self) -> bool:
        """Whether this run's steps replay as one CUDA graph: ``config.cuda_graph`` (unset: wherever the
        run allows it) in a run of one process."""
        c = self.config
        return c.cuda_graph is not False and self.processes.world_size == 1 and c.cuda_graph_unsupported() is None

    def _diverged_message(self, loss: float) -> str:
        """What a diverged run kept on disk, and what to do next (:meth:`Checkpointer.diverged_message`)."""
        return self.checkpointer.diverged_message(loss, self.step)

    # ------------------------------------------------------------------ the loop
    def train(self) -> dict[str, Any]:
        """Train until a stop rule holds; returns a summary.

        The run directory is locked for the whole call (a second process training into it gets a
        ``ValueError`` naming this one). SIGINT (Ctrl-C) and SIGTERM finish the current step, save a
        checkpoint and raise :class:`TrainingInterrupted`; :meth:`resume` continues from there.
        Raises :class:`TrainingDivergedError` when the loss becomes NaN or inf. Unless the caller
        chose a thread count, torch uses the cores other processes leave free
        (:func:`reach.threads.thread_policy`). In a distributed run every process calls this; rank 0
        alone locks, writes and reports."""
        main = self.processes.main
        with (
            self.run.lock() if main else contextlib.nullcontext(),
            deferred_signals() as stop,
            thread_policy(),
            matmul_precision(self.config.matmul_precision),
        ):
            self.step_objective = self.processes.wrap(self.objective)
            try:
                return self._train(stop)
            finally:
                # DistributedDataParallel is dropped here, while the process group lives: its Reducer must
                # not be the group's last owner, whose destructor would then run holding the GIL and wait
                # for gloo's threads, which may need the GIL (a deadlock, pytorch/pytorch#56297)
                self.step_objective = self.objective

    def _train(self, stop: dict[str, int]) -> dict[str, Any]:
        c = self.config
        main = self.processes.main
        if main:
            self.run.write_config(c)
        with ProgressReport(self.run if main else None, c, self.evaluator, self.step, self.progress) as report:
            reason = self._run_steps(report, stop)
            if main and c.snapshots and not self.run.snapshot_path(c.snapshots).exists():
                self._snapshot(c.snapshots)  # a run stopped early (target loss): its end is the last snapshot
            self._save()
        return {
            "run_dir": str(self.run_dir),
            "steps": self.step,
            "wall_time_s": self.wall,
            "loss_ema": self.loss_ema,
            "stopped": reason,
        }

    def _run_steps(self, report: ProgressReport, stop: dict[str, int]) -> str:
        """Optimise, report, snapshot and checkpoint until a stop rule holds (returned) or a signal
        comes (:class:`TrainingInterrupted`, after a checkpoint)."""
        c = self.config
        last_checkpoint = report.started
        reason = self.stop_reason()
        # snapshots past the checkpoint (a killed run) are retaken as the resumed run passes them
        snapshots_taken = self._snapshots_due()
        while reason is None:
            record = self._optimise()
            report.stepped()
            if self.step % c.log_every == 0 or self.stop_reason():
                report.line(self.step, self.wall, record, self.network, stopping=self.stop_reason() is not None)
            if (due := self._snapshots_due()) > snapshots_taken:
                self._snapshot(due)
                snapshots_taken = due
            # the processes of a distributed run act together: on a signal any of them caught, and on
            # rank 0's checkpoint timer
            checkpoint_due, interrupted = self.processes.any(
                self.processes.main and time.perf_counter() - last_checkpoint >= c.checkpoint_every_s, bool(stop)
            )
            if checkpoint_due:
                self._save()
                last_checkpoint = time.perf_counter()
            if interrupted:
                self._save()
                signal_name = caught_signal_name(stop) if stop else "a signal to another process"
                raise TrainingInterrupted(
                    f"{signal_name} at step {self.step}: saved {self.checkpoint_path}; continue "
                    f"with `reach train --resume {self.run_dir}`"
                )
            reason = self.stop_reason()
        return reason
