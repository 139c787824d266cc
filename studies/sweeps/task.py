"""One sweep task: train one (layout, seed), then score each of its snapshots. Resumable.

:func:`run_task` is a plain top-level function of picklable arguments, so local worker processes and
Ray workers run the very same code. A task's files live in ``OUT/runs/<layout>-s<seed>/``:

* the training run (``config.json``, ``checkpoint.pt``, ``metrics.jsonl``, ``snapshots/NNN.pt``),
  continued with :meth:`training.Trainer.resume` when a previous sweep was interrupted;
* ``scores.json``: the score of every evaluated snapshot, keyed by the snapshot file's
  :func:`studies.batch_verification.fingerprint` (path, size, modification time) and by the scorer's
  settings, rewritten atomically after each snapshot, so a task interrupted during evaluation
  keeps what it had scored.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from reach.atomic import atomic_path
from reach.result_columns import current_names
from reach.threads import apply_thread_policy
from studies.sweeps.scoring import GroundTruthScorer, RolloutScorer
from studies.sweeps.spec import SweepSpec
from training import Trainer

_SCORERS: dict[str, Any] = {}  # one scorer per worker process and settings (ground truths are large)


def run_dir(out: str | os.PathLike, layout: str, seed: int) -> Path:
    return Path(out) / "runs" / f"{layout}-s{seed}"


def _scorer(spec: Any, groundtruth: str | None) -> Any:
    ident = json.dumps([spec.to_dict(), groundtruth], sort_keys=True, default=str)
    if ident not in _SCORERS:
        system = spec.build_system()
        if spec.evaluation == "groundtruth":
            if groundtruth is None:
                raise ValueError("a ground-truth evaluation needs the ground-truth file")
            scorer = GroundTruthScorer(system, groundtruth, spec.eval_time, spec.slice_value)
        else:
            scorer = RolloutScorer(
                system, spec.samples, spec.scenario_samples, spec.eval_seed, spec.device, spec.pairwise
            )
        _SCORERS.clear()
        _SCORERS[ident] = scorer
    return _SCORERS[ident]


def _train(spec: Any, layout: str, seed: int, directory: Path) -> None:
    config = spec.train_config(layout, seed)
    trainer = Trainer.open(config, directory, progress=False)
    if trainer.config.to_json() != config.to_json():
        raise ValueError(f"{directory} holds a run with another configuration than this sweep's")
    if trainer.needs_training():
        trainer.train()


def _read_scores(path: Path, key: dict[str, Any]) -> dict[str, Any]:
    try:
        data = current_names(json.loads(path.read_text()))
    except (OSError, json.JSONDecodeError):
        return {}
    return data.get("snapshots", {}) if data.get("scorer") == key else {}


def run_task(
    out: str,
    spec_dict: dict[str, Any],
    layout: str,
    seed: int,
    groundtruth: str | None = None,
    threads: int | None = None,
) -> list[dict[str, Any]]:
    """Train (or finish training) ``layout`` with ``seed`` and score its snapshots; one row per snapshot.

    Rows hold ``layout``, ``seed``, ``snapshot``, ``fraction`` (of the run), ``step``, ``wall``
    (training seconds, evaluation excluded), ``steps_per_s`` and the scorer's metrics.
    """
    # lazy: the safety stack only when a task scores
    from safety.value_loading import load_value_function
    from studies.batch_verification import fingerprint

    if threads:
        apply_thread_policy(threads)  # the sweep's per-run count, which training then keeps
    if not Path(out).is_dir():
        raise ValueError(f"sweep directory {out} is not visible here (on a cluster it must be on shared storage)")
    spec = SweepSpec.from_dict(spec_dict)
    directory = run_dir(out, layout, seed)
    _train(spec, layout, seed, directory)
    scorer = _scorer(spec, groundtruth)
    scores_path = directory / "scores.json"
    scores = _read_scores(scores_path, scorer.key)
    rows = []
    for index in range(1, spec.snapshots + 1):
        path = directory / "snapshots" / f"{index:03d}.pt"
        if not path.exists() or not spec.rolled_out(index):
            continue
        meta = json.loads(path.with_suffix(".json").read_text())
        version = fingerprint(str(path))
        cached = scores.get(path.name)
        if cached is None or cached.get("fingerprint") != version:
            start = time.perf_counter()
            vf = load_value_function(path, device=spec.device).value_function
            metrics = scorer(vf)
            cached = {"fingerprint": version, "metrics": metrics, "eval_seconds": time.perf_counter() - start}
            scores[path.name] = cached
            with atomic_path(scores_path) as tmp:
                Path(tmp).write_text(json.dumps({"scorer": scorer.key, "snapshots": scores}, indent=1, default=str))
        wall = float(meta["wall_time_s"])
        rows.append(
            {
                "layout": layout,
                "seed": seed,
                "snapshot": index,
                "fraction": index / spec.snapshots,
                "step": int(meta["steps"]),
                "wall": wall,
                "steps_per_s": int(meta["steps"]) / max(wall, 1e-9),
                "eval_seconds": cached["eval_seconds"],
                **cached["metrics"],
            }
        )
    return rows
