"""A run's schedule (progress, learning rate, time range, stop rules), from its counters so resumes keep to it.

Every rule is a function of the configuration and the run's counters (step, seconds of training,
loss average) alone: a resumed run follows the schedule of an uninterrupted one.
"""

from __future__ import annotations

import math

from training.config import TrainConfig
from training.network import LEARNED_BOUNDARY


class Schedule:
    """The schedule of a run of ``config`` on a system whose horizon is ``horizon``."""

    def __init__(self, config: TrainConfig, horizon: float) -> None:
        self.config = config
        self.horizon = horizon

    def progress(self, step: int, wall: float) -> float:
        """How far the run is, in [0, 1], by its step or time budget (whichever is further)."""
        c = self.config
        parts = []
        if c.steps is not None:
            parts.append(step / c.steps)
        if c.budget_s is not None:
            parts.append(wall / c.budget_s)
        return min(1.0, max(parts)) if parts else 0.0

    def learning_rate(self, frac: float) -> float:
        """Constant, or cosine from ``lr`` down to ``lr_final`` over the run."""
        c = self.config
        if c.schedule == "constant":
            return c.lr
        return c.lr_final + 0.5 * (c.lr - c.lr_final) * (1 + math.cos(math.pi * frac))

    def time_range(self, frac: float) -> float:
        """The largest time-to-go sampled at ``frac``: the curriculum grows it from 0 to the horizon
        (after a vanilla run's boundary-only pretraining)."""
        c = self.config
        if c.curriculum <= 0:
            return self.horizon
        pre = c.pretrain if c.parameterisation in LEARNED_BOUNDARY else 0.0
        grow = (frac - pre) / c.curriculum if frac > pre else 0.0
        return self.horizon * min(1.0, max(0.0, grow))

    def trains_pde(self, frac: float) -> bool:
        """Whether the HJI residual counts at ``frac`` (a vanilla run pretrains on its boundary alone)."""
        c = self.config
        return not (c.parameterisation in LEARNED_BOUNDARY and frac < c.pretrain)

    def snapshots_due(self, frac: float) -> int:
        """How many snapshots the run's progress calls for (0 .. ``config.snapshots``)."""
        k = self.config.snapshots
        return min(k, int(frac * k + 1e-9))

    def stop_reason(self, step: int, wall: float, loss_ema: float | None) -> str | None:
        """Why the run would stop now (a stop rule that holds), or None while it has work left."""
        c = self.config
        if c.steps is not None and step >= c.steps:
            return f"reached {c.steps} steps"
        if c.budget_s is not None and wall >= c.budget_s:
            return f"reached the time budget of {c.budget_s:.0f} s"
        if c.target_loss is not None and loss_ema is not None and loss_ema <= c.target_loss:
            return f"loss {loss_ema:.3g} reached the target {c.target_loss:g}"
        return None
