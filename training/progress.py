"""A run's progress reports (metrics lines, evaluations when due, a bar), timed so steps/s count training only.

The steps/s window restarts at each metrics line and after an evaluation (evaluating is not training).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

from tqdm.auto import tqdm

from training.config import TrainConfig
from training.network import NeuralValueFunction, ValueNetwork
from training.run_directory import RunDirectory

#: scores a network during training (e.g. :class:`training.evaluate.ReferenceEvaluator`); its numbers join
#: the metrics line
Evaluator = Callable[[NeuralValueFunction], dict[str, float]]


class StepRecord(NamedTuple):
    """What one optimisation step used and measured."""

    lr: float
    tmax: float
    terms: dict[str, float]


class ProgressReport:
    """Reports a run of ``config`` from ``step`` on: lines to the metrics log of ``run`` and a progress bar
    (shown if ``progress``). A context manager: the bar and the log close when its block ends.

    ``run=None`` reports nothing (the processes of a distributed run other than rank 0, which reports
    for them all); its timer still starts."""

    def __init__(
        self, run: RunDirectory | None, config: TrainConfig, evaluator: Evaluator | None, step: int, progress: bool
    ) -> None:
        self.config = config
        self.evaluator = evaluator
        self.log = None if run is None else run.metrics_log(step, config.tensorboard)
        #: when reporting started (the loop's checkpoint timer starts here too)
        self.started = self.last_eval = time.perf_counter()
        self.window_start, self.window_steps = time.perf_counter(), 0
        # without an explicit `disable`, tqdm honours TQDM_DISABLE=1 (CI) and hides itself off a terminal
        self.bar = tqdm(
            total=config.steps,
            initial=step,
            desc=f"{config.system} {config.layout}",
            unit="step",
            **({} if progress and run is not None else {"disable": True}),
        )

    def stepped(self) -> None:
        """Count a step done."""
        self.window_steps += 1
        self.bar.update(1)

    def line(self, step: int, wall: float, record: StepRecord, network: ValueNetwork, stopping: bool) -> None:
        """Write the metrics line of ``step`` (``wall`` seconds of training in), evaluating ``network``
        when ``eval_every_s`` has passed or the run is ``stopping``, and update the bar."""
        c = self.config
        now = time.perf_counter()
        rate = self.window_steps / max(now - self.window_start, 1e-9)
        self.window_start, self.window_steps = now, 0
        if self.log is None:
            return
        row = {
            "step": step,
            "wall": round(wall, 3),
            "lr": record.lr,
            "tmax": record.tmax,
            "steps_per_s": round(rate, 3),
            "points_per_s": round(rate * c.points, 1),
            **record.terms,
        }
        if self.evaluator is not None and (now - self.last_eval >= c.eval_every_s or stopping):
            row.update(self.evaluator(NeuralValueFunction(network)))
            self.last_eval = self.window_start = time.perf_counter()  # evaluation is not training time
        self.log.write(row)
        left = (c.budget_s - wall) if c.budget_s else None
        self.bar.set_postfix(
            loss=f"{record.terms['loss']:.3g}",
            steps_s=f"{rate:.1f}",
            left=f"{left:.0f}s" if left is not None else "-",
        )

    def close(self) -> None:
        self.bar.close()
        if self.log is not None:
            self.log.close()

    def __enter__(self) -> ProgressReport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
