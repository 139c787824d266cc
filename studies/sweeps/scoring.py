"""How a sweep scores one network snapshot: against a grid ground truth, or by rollouts.

A scorer is built once per worker process and applied to every snapshot of a task. Its ``key``
names everything its numbers depend on, so cached scores are reused only under the same settings.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Protocol

from reach.systems import ControlAffineSystem
from reach.value_function import ValueFunction


class Scorer(Protocol):
    key: dict[str, Any]
    #: (metric, higher is better) pairs the report plots and ranks by, most important first
    headline: tuple[tuple[str, bool], ...]

    def __call__(self, vf: ValueFunction) -> dict[str, float]: ...


class GroundTruthScorer:
    """Value MSE and IoU of ``{V <= 0}`` at ``t`` over every grid node and over one slice."""

    headline = (("iou_volume", True), ("mse_volume", False), ("iou_slice", True), ("mse_slice", False))

    def __init__(
        self, system: ControlAffineSystem, path: str | os.PathLike, t: float | None, slice_value: float | None
    ):
        # lazy: the grid solution and its evaluator only for ground-truth scoring
        from groundtruth.solution import GridSolution
        from training.accuracy import ReferenceEvaluator

        solution = GridSolution.load(path, outside="clamp")
        system.require_same_physics(solution.system, f"ground truth {path}")
        t = float(solution.times[-1]) if t is None else float(t)
        if not float(solution.times[0]) <= t <= float(solution.times[-1]) + 1e-9:
            raise ValueError(f"eval time {t} lies outside the ground truth's times [0, {float(solution.times[-1])}]")
        self.solution = solution
        self._evaluate = ReferenceEvaluator(solution, t, slice_value=slice_value)
        st = Path(path).stat()
        self.key = {
            "kind": "groundtruth",
            "file": str(Path(path).resolve()),
            "size": st.st_size,
            "t": t,
            "slice_value": slice_value,
        }

    def __call__(self, vf: ValueFunction) -> dict[str, float]:
        return self._evaluate(vf)


class RolloutScorer:
    """Violation rate, collision rate, delta-level and scenario volume from rollouts of the policy."""

    headline = (("violation_rate", False), ("delta", False), ("scenario_volume", True), ("collision_rate", False))

    #: the columns of :func:`safety.verification.verify.verify` a sweep keeps (each kind of problem fills its own:
    #: :data:`safety.verification.metrics.KIND_COLUMNS`)
    KEEP = (
        "problem",
        "violation_rate",
        "false_safe_rate",
        "false_unsafe_rate",
        "collision_rate",
        "false_reachable_rate",
        "false_unreachable_rate",
        "failure_rate",
        "reachable_fraction",
        "delta",
        "delta_raw",
        "safe_fraction",
        "eps",
        "scenario_volume",
        "scenario_failures",
        "rollout_seconds",
    )

    def __init__(
        self,
        system: ControlAffineSystem,
        samples: int,
        scenario_samples: int | None,
        seed: int,
        device: str = "cpu",
        pairwise: str | os.PathLike | None = None,
    ) -> None:
        from safety.verification.verify import (  # lazy: the safety stack only for rollout scoring
            VerifySettings,
            sample_states,
        )

        # sweeps score many snapshots: no robust scenario verification (it needs about a million rollouts)
        self.settings = VerifySettings(samples=samples, scenario_samples=scenario_samples, seed=seed, robust_samples=0)
        self.states = sample_states(system, samples, seed)
        self.device = device
        settings = {k: v for k, v in self.settings.to_dict().items() if k not in ("target_eps", "robust_samples")}
        self.key = {"kind": "rollout", "system": system.config(), **settings, "pairwise": None}
        self.union_values = None
        if pairwise is not None:  # containment in the union of pairwise BRTs (a sound model misses none)
            from studies.batch_verification import pairwise_union_values  # lazy: only with a pairwise union

            self.union_values = pairwise_union_values(pairwise, system, self.states, system.horizon)
            self.key["pairwise"] = {"file": str(Path(pairwise).resolve()), "size": Path(pairwise).stat().st_size}

    def __call__(self, vf: ValueFunction) -> dict[str, float]:
        # lazy: the safety stack only for rollout scoring
        from safety.verification.metrics import KIND_COLUMNS, containment_statistics
        from safety.verification.verify import values_at, verify

        row = verify(vf, self.states, self.settings, device=self.device, progress=False)
        if self.settings.fresh_samples == 0:  # no guarantee asked for: the volume a scenario set would cover
            row["scenario_volume"] = row[KIND_COLUMNS[row["problem"]][3]]
        out = {k: row[k] for k in self.KEEP if k in row}
        if self.union_values is not None:
            learned = values_at(vf, self.states, vf.system.horizon, device=self.device)
            out.update(containment_statistics(self.union_values, learned))
        return out


def headline_of(evaluation: str) -> tuple[tuple[str, bool], ...]:
    """The headline metrics of an evaluation kind, without building a scorer."""
    return GroundTruthScorer.headline if evaluation == "groundtruth" else RolloutScorer.headline
