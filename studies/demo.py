"""The one-command demo: ground truth, a short training run, verification, filter evaluation, report.

:func:`run_demo` does on Air3D what the README's results do at full size, small enough for a
laptop CPU: solve the 101^3 grid ground truth (horizon 1.1), train the default layout for a few
minutes, verify it and the ground truth by rollouts, evaluate the safety filter against a
worst-case pursuer, and write ``report.md`` with its table, slice plot, trade-off plot and an
episode GIF. Every step is skipped when its output already exists, so an interrupted demo resumes.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from reach.atomic import atomic_path
from reach.validation import check_float, check_int, check_seed, settings_from


@dataclass(frozen=True)
class DemoSettings:
    """How large the demo is; ``reach demo`` reads its option defaults from here. Checked when made.

    Attributes:
        budget_s: the training run's wall-clock budget in seconds.
        grid: the ground truth's nodes per dimension (at least 5).
        samples: verification rollouts per value function.
        episodes: filter-evaluation episodes.
        seed: the seed of the verification states and of the episodes.
        compile: whether the grid solver compiles (``None``: it decides from the work,
            :class:`~groundtruth.settings.SolverSettings`).
    """

    budget_s: float = 180.0
    grid: int = 101
    samples: int = 10_000
    episodes: int = 500
    seed: int = 0
    compile: bool | None = None

    def __post_init__(self) -> None:
        check_float("budget_s", self.budget_s, 0, low_open=True)
        check_int("grid", self.grid, 5)
        check_int("samples", self.samples, 1)
        check_int("episodes", self.episodes, 1)
        check_seed("seed", self.seed)
        if not isinstance(self.compile, (bool, type(None))):
            raise ValueError(f"compile must be True, False or None (decide from the work), got {self.compile!r}")


def run_demo(
    out: str | os.PathLike = "reach-demo",
    settings: DemoSettings | None = None,
    *,
    progress: bool = True,
    log: Any = print,
    **options: Any,
) -> Path:
    """Run the Air3D demo into ``out``; returns the report's path.

    ``settings`` (:class:`DemoSettings`, default: its defaults) sizes the demo; its fields may also
    be given as keywords (``grid=21, samples=300``), each replacing its field."""
    demo = settings_from(DemoSettings, settings, options, "demo")
    budget_s, grid, samples, episodes, seed = demo.budget_s, demo.grid, demo.samples, demo.episodes, demo.seed
    # lazy: the demo's stack only when it runs (the CLI's parser imports this module)
    from groundtruth.settings import SolverSettings
    from groundtruth.solution import GridSolution
    from groundtruth.solver import solve
    from reach.systems import Air3D
    from safety.value_loading import load_value_function
    from safety.verification.verify import VerifySettings
    from studies.batch_verification import SourceLoading, evaluate_many, markdown_table
    from studies.filter_study import run_filter_study
    from studies.filter_tables import filter_table
    from studies.plots import plot_brt_slices
    from training import TrainConfig, Trainer
    from training.recipes import CPU_3D

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    system = Air3D()
    times = [round(0.05 * k, 4) for k in range(23)]  # 0 .. 1.1

    gt_path = out / "air3d_gt.npz"
    if not gt_path.exists():
        log(f"[1/5] ground truth: Air3D on a {grid}^3 grid to t = 1.1")
        solve(system, grid, times, settings=SolverSettings(compile=demo.compile), progress=progress).save(gt_path)
    gt = GridSolution.load(gt_path, outside="clamp")

    run = out / "air3d-ssssl"
    config = TrainConfig(system="air3d", layout="ssssl", budget_s=budget_s, seed=seed, **CPU_3D)
    trainer = Trainer.open(config, run, progress=progress)  # an interrupted demo continues its run
    if trainer.needs_training():
        log(f"[2/5] training layout ssssl for {trainer.config.budget_s:.0f} s (the CPU_3D recipe)")
        trainer.train()
    network = load_value_function(run).value_function

    log(f"[3/5] verification: {samples} rollouts each, IoU/MSE against the grid at t = 1.0")
    results = out / "verification.csv"
    rows = evaluate_many(
        [str(gt_path), str(run)],
        results,
        VerifySettings(samples=samples, seed=seed, robust_samples=0),  # robust needs ~1M rollouts
        loading=SourceLoading(system=system),
        ground_truth=gt_path,
        gt_time=1.0,
        progress=progress,
    )
    plot_brt_slices([("trained ssssl", network)], out / "slices.png", t=1.0, reference=gt)

    log(f"[4/5] safety filter: {episodes} attacked episodes from outside the grid BRT, and a GIF of three")
    filter_rows = run_filter_study(
        "air3d",
        [("trained ssssl", network), ("grid truth", gt)],  # the first one filters in the GIF
        out / "filter.csv",
        thresholds=(0.0, 0.06),
        episodes=episodes,
        seed=seed,
        pursuer=gt,
        start_outside=gt,
        gif=out / "episodes.gif",
        gif_threshold=0.06,
        title="Air3D, worst-case pursuer",
    ).rows
    log("[5/5] report")
    report = out / "report.md"
    text = f"""# reach demo: Air3D

Ground truth: {grid}^3 grid, horizon 1.1. Trained network: layout ssssl, width 128, {budget_s:.0f} s
of `reach train` defaults with {trainer.config.points} points a step (`training.recipes.CPU_3D`; run
directory `{run.name}`). Total wall time {time.perf_counter() - start:.0f} s.

## Verification ({samples} rollouts per value function, Euler dt 0.0025, worst-case pursuer)

{markdown_table(rows)}

![BRT slices](slices.png)

## Safety filter ({episodes} episodes from outside the grid BRT, pursuer playing the grid's d*)

{filter_table(filter_rows)}

![trade-off](filter_tradeoff.png)

![episodes](episodes.gif)
"""
    with atomic_path(report) as tmp:
        Path(tmp).write_text(text)
    return report
