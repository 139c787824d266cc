"""``reach sweep``: train every (layout, seed) on a budget, score snapshots along the way, report.

A sweep directory::

    OUT/sweep.json                 the spec (see :mod:`studies.sweeps.spec`)
    OUT/groundtruth.npz            the grid ground truth, solved once (ground-truth evaluations only)
    OUT/runs/<layout>-s<seed>/     each task's training run, snapshots and cached scores
    OUT/results.{json,csv,md}      every (layout, seed, snapshot) row, rewritten as tasks finish
    OUT/pareto.png                 accuracy against training time, one curve per layout
    OUT/slices.png                 BRT slices of the best and worst layouts' final networks
    OUT/report.md                  the tables, plots and the paper's claims checked on these data

Interrupting a sweep loses at most the work since each task's last checkpoint; running the same
command again continues it (finished tasks are read back, not redone).
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from reach.atomic import atomic_path
from reach.locking import run_lock
from reach.validation import check_int, check_output_dir
from safety.verification.sharding import check_ray_ready
from studies.sweeps.report import claims_table, final_rows, plot_pareto, rank_layouts, summary_table
from studies.sweeps.scoring import headline_of
from studies.sweeps.spec import SweepSpec, store_spec
from studies.sweeps.task import run_dir
from studies.tables import write_results

RESULTS_FORMAT = "reach.sweep-results.v1"


def _ground_truth(spec: SweepSpec, out: Path, progress: bool, log: Callable[[str], Any]) -> str | None:
    """The ground-truth file (given, or solved once into ``OUT/groundtruth.npz``)."""
    if spec.evaluation != "groundtruth":
        return None
    if spec.groundtruth is not None:
        if not Path(spec.groundtruth).exists():
            raise ValueError(f"ground truth {spec.groundtruth} does not exist")
        return str(Path(spec.groundtruth).resolve())
    path = out / "groundtruth.npz"
    if not path.exists():
        from groundtruth.solver import solve  # lazy: the grid solver only when a ground truth must be solved

        system = spec.build_system()
        t = system.horizon if spec.eval_time is None else spec.eval_time
        times = [t * k / 20 for k in range(21)]
        log(f"ground truth: {spec.system} on a {spec.grid}^{system.state_dim} grid to t = {t:g} -> {path}")
        solve(system, spec.grid, times, progress=progress).save(path)  # compiles only where it pays off
    return str(path.resolve())


def headline(spec: SweepSpec, rows: list[dict[str, Any]]) -> tuple[tuple[str, bool], ...]:
    """The metrics tables and plots show: the scorer's, plus union containment where it was measured."""
    base = headline_of(spec.evaluation)
    if any("containment_miss_rate" in r for r in rows):
        base = (*base, ("containment_miss_rate", False))
    return base


def machine() -> str:
    """One line naming the machine a study's driver ran on."""
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, torch {torch.__version__}, "
        f"Python {platform.python_version()}"
    )


def run_sweep(
    spec: SweepSpec,
    out: str | os.PathLike,
    backend: str = "local",
    workers: int = 1,
    threads: int | None = None,
    address: str | None = None,
    progress: bool = True,
    log: Callable[[str], Any] = print,
) -> tuple[Path, list[tuple[str, int, str]]]:
    """Run (or continue) the sweep into ``out``; returns the report's path and the failed tasks
    as ``(layout, seed, error)``."""
    spec.validate()
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    if backend == "ray":
        check_ray_ready(address)  # Ray missing or an address nothing answers at: refused before any run
    elif address is not None:
        raise ValueError("--address needs --backend ray")
    check_int("workers", workers, 1)
    if threads is not None:
        check_int("threads", threads, 1)
    out = check_output_dir(out, "sweep")
    out.mkdir(parents=True, exist_ok=True)
    with run_lock(out):
        return _run_locked(spec, out, backend, workers, threads, address, progress, log)


def _run_locked(
    spec: SweepSpec,
    out: Path,
    backend: str,
    workers: int,
    threads: int | None,
    address: str | None,
    progress: bool,
    log: Callable[[str], Any],
) -> tuple[Path, list[tuple[str, int, str]]]:
    from studies.sweeps.backends import run_local, run_ray  # lazy: worker pools and Ray only when a sweep runs

    store_spec(spec, out)
    groundtruth = _ground_truth(spec, out, progress, log)
    if threads is None and backend == "local" and workers > 1:
        threads = max(1, (os.cpu_count() or 1) // workers)  # workers share the cores instead of fighting
    spec_dict = spec.to_dict()
    tasks = [(str(out), spec_dict, layout, seed, groundtruth, threads) for layout, seed in spec.tasks()]
    outcomes = run_local(tasks, workers) if backend == "local" else run_ray(tasks, address)
    rows_by_task: dict[tuple[str, int], list[dict[str, Any]]] = {}
    failed: list[tuple[str, int, str]] = []
    start = time.perf_counter()
    bar = tqdm(total=len(tasks), desc=f"sweep {spec.system}", unit="run", **({} if progress else {"disable": True}))
    for args, result in outcomes:
        layout, seed = args[2], args[3]
        if isinstance(result, BaseException):
            failed.append((layout, seed, f"{type(result).__name__}: {result}"))
            log(f"sweep: {layout} seed {seed} failed: {result}")
        else:
            rows_by_task[(layout, seed)] = result
        _write_rows(out, spec, rows_by_task, failed)
        bar.update(1)
    bar.close()
    rows = _in_task_order(spec, rows_by_task)
    if backend == "ray":
        execution = f"Ray tasks ({'cluster ' + address if address else 'local Ray instance'}), one CPU each"
    else:
        per_run = f"{threads} torch thread(s)" if threads else "torch's default threads"
        execution = f"{workers} local run(s) at a time, {per_run} each"
    report = write_report(spec, out, rows, failed, groundtruth, time.perf_counter() - start, execution)
    return report, failed


def _in_task_order(spec: SweepSpec, rows_by_task: dict) -> list[dict[str, Any]]:
    """The finished tasks' rows, layouts then seeds in the spec's order (not the order they finished)."""
    return [r for layout, seed in spec.tasks() for r in rows_by_task.get((layout, seed), [])]


def _write_rows(out: Path, spec: SweepSpec, rows_by_task: dict, failed: list) -> None:
    rows = _in_task_order(spec, rows_by_task)
    header = {"format": RESULTS_FORMAT, "spec": spec.to_dict(), "failed": failed}
    table = summary_table(rows, headline(spec, rows)) if rows else "(no results yet)"
    write_results(out / "results", header, rows, table)


def _slice_plot(spec: SweepSpec, out: Path, rows: list[dict[str, Any]], groundtruth: str | None) -> Path | None:
    """BRT slices of the best and the worst layout (by the first headline metric), the seed nearest
    its layout's mean, final snapshot; the ground truth filled where there is one."""
    # lazy: loading and plotting only for the report's slices
    from safety.value_loading import load_value_function
    from studies.plots import plot_brt_slices

    metric, higher = headline_of(spec.evaluation)[0]
    ranked = rank_layouts(rows, metric, higher)
    if not ranked:
        return None
    picks = [ranked[0]] if len(ranked) == 1 else [ranked[0], ranked[-1]]
    finals = final_rows(rows)
    curves = []
    for (layout, mean), tag in zip(picks, ("best", "worst")):
        row = min(finals[layout], key=lambda r: abs(r[metric] - mean))
        path = run_dir(out, layout, row["seed"]) / "snapshots" / f"{row['snapshot']:03d}.pt"
        vf = load_value_function(path).value_function
        curves.append((f"{tag}: {layout} (seed {row['seed']}, {metric} {row[metric]:.3g})", vf))
    reference = None
    t = None
    if groundtruth is not None:
        from groundtruth.solution import GridSolution  # lazy: the grid solution only for ground-truth sweeps

        reference = GridSolution.load(groundtruth, outside="clamp")
        t = float(reference.times[-1]) if spec.eval_time is None else spec.eval_time
    return plot_brt_slices(curves, out / "slices.png", t=t, reference=reference)


def _effort(rows: list[dict[str, Any]]) -> str:
    """Training and scoring time summed over the runs (what the study cost, whichever call did it)."""
    finals: dict[tuple[str, int], float] = {}
    for r in rows:
        finals[(r["layout"], r["seed"])] = max(finals.get((r["layout"], r["seed"]), 0.0), float(r["wall"]))
    scoring = sum(float(r.get("eval_seconds", 0.0)) for r in rows)
    trained = sum(finals.values()) / 60
    return f"{len(finals)} runs trained {trained:.0f} min and were scored in {scoring / 60:.1f} min in all"


def write_report(
    spec: SweepSpec,
    out: Path,
    rows: list[dict[str, Any]],
    failed: list[tuple[str, int, str]],
    groundtruth: str | None,
    seconds: float,
    execution: str = "",
) -> Path:
    """``report.md`` (and its plots) from the rows; returns its path."""
    metrics = headline(spec, rows)
    budget = f"{spec.budget_s:.0f} s" if spec.budget_s is not None else f"{spec.steps} steps"
    parts = [
        f"# Layout sweep: {spec.system}",
        "",
        f"{len(spec.layouts)} layouts x {len(spec.seeds)} seeds, width {spec.width}, {budget} of training each "
        f"({', '.join(f'{k}={v}' for k, v in spec.train.items()) or 'reach train defaults'}), scored at "
        f"{spec.snapshots} evenly spaced snapshots. Training time excludes evaluation. Machine: {machine()}; "
        f"{execution + '; ' if execution else ''}{_effort(rows)}; this call took {seconds:.0f} s.",
        "",
    ]
    if spec.evaluation == "groundtruth":
        from groundtruth.solution import GridSolution  # lazy: the grid solution only for ground-truth sweeps

        gt = GridSolution.load(groundtruth)
        t = float(gt.times[-1]) if spec.eval_time is None else spec.eval_time
        parts.append(
            f"Accuracy against the grid ground truth `{Path(groundtruth).name}` "
            f"({'x'.join(str(n) for n in gt.grid.shape)} nodes) at t = {t:g}: value MSE and IoU of "
            f"{{V <= 0}} over every grid node (vol.) and over the slice "
            f"{gt.system.state_names[gt.system.reference_slice()[0]]} = {spec.slice_value:g}."
        )
    else:
        parts.append(
            f"Rollouts of the learned policy from {spec.samples} uniform states (seed {spec.eval_seed}): violation "
            "rate (both kinds), collision rate, delta-level and scenario volume (the fraction of the box with "
            "V > delta)"
            + (
                f", and the share of states in the union of pairwise BRTs `{Path(spec.pairwise).name}` that a "
                "network calls safe (misses union; a sound model misses none)."
                if spec.pairwise
                else "."
            )
        )
    parts.append(
        "The time curriculum and learning-rate schedule follow each run's budget, so an early snapshot is "
        "a run cut short, not a run trained for that long."
    )
    if not rows:
        parts += ["", "No results: every task failed."]
    else:
        parts += ["", "## Final snapshot, mean ± std over seeds (best first)", "", summary_table(rows, metrics)]
        pareto = plot_pareto(rows, out / "pareto.png", metrics, title=f"{spec.system}: accuracy against time")
        parts += ["", "## Accuracy against training time", "", f"![Pareto plot]({pareto.name})"]
        slices = _slice_plot(spec, out, rows, groundtruth)
        if slices is not None:
            parts += ["", "## Best and worst layouts", "", f"![slices]({slices.name})"]
        parts += [
            "",
            "## The seed paper's claims on these data",
            "",
            claims_table(rows, metrics),
            "",
            "Statistics are sign-adjusted (> 0 agrees with the claim); p is the chance of a statistic at least "
            "as large if the layouts were labelled at random (exact permutations over the layouts). With few "
            'layouts and seeds, read p > 0.05 as "not established", not as "refuted".',
        ]
    if failed:
        parts += ["", "## Failed tasks", ""] + [f"- `{layout}` seed {seed}: {err}" for layout, seed, err in failed]
    parts += ["", "Data: `results.json`, `results.csv`; each run in `runs/<layout>-s<seed>/`."]
    report = out / "report.md"
    with atomic_path(report) as tmp:
        Path(tmp).write_text("\n".join(parts) + "\n")
    return report
