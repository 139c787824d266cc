"""9D ablation: each change to the default recipe is one row, same seeds, same steps, scored the same way.

Run (resumable; every stage skips what is already done)::

    python benchmarks/nine_d_ablation.py train  --out runs/studies/9d-ablation
    python benchmarks/nine_d_ablation.py score  --out runs/studies/9d-ablation
    python benchmarks/nine_d_ablation.py report --out runs/studies/9d-ablation

Rows (``--rows``, default all): ``baseline`` (the defaults) and each change of :data:`ROWS`
(:data:`studies.step_budget_study.CHANGES`, which the layout study adds with ``--with``), trained
for ``--minutes`` of the quiet 2-core rate (as steps: ``minutes x --steps-per-minute``, so a run that
shares the cores trains what a quiet one trains in that time) for every seed in ``--seeds``. The
baseline reuses the 9D accuracy-against-time study's run of the same budget and seed where one
exists (``--study``; same command, same defaults), so the study and the ablation share their
baseline. ``score`` verifies as ``reach evaluate`` does, with the study's settings (``--samples``
uniform states, ``--scenario-samples`` fresh ones, the union of pairwise BRTs); ``report`` prints one
row per change, the mean over seeds and each seed's value.

The stages are :mod:`studies.step_budget_study`'s and the table :mod:`studies.step_budget_report`'s;
this script names the runs and parses the command line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from reach_cli import guarded
from studies.step_budget_report import BASELINE, print_seed_table, read_metrics
from studies.step_budget_study import (
    CHANGES,
    PlannedRun,
    Scoring,
    add_run_arguments,
    change_settings,
    run_path,
    score_runs,
    stage_parser,
    train_runs,
)

#: the changes, each as the training settings that make it (the baseline adds none)
ROWS = CHANGES


def run_dir(args: argparse.Namespace, row: str, seed: int) -> Path:
    """The run of a row and seed: the study's for the baseline where it exists, else the ablation's."""
    if row == "baseline":
        study = run_path(args.study, BASELINE, args.minutes, seed)
        if (study / "checkpoint.pt").exists():
            return study
    return run_path(args.out, row, args.minutes, seed)


def train(args: argparse.Namespace) -> int:
    steps = round(args.minutes * args.steps_per_minute)
    runs = [
        PlannedRun(run_dir(args, row, seed), steps, seed, change_settings(row, args.pairwise))
        for row in args.rows
        for seed in args.seeds
    ]
    return train_runs(runs, args.device)


def score(args: argparse.Namespace) -> int:
    runs = [run_dir(args, row, seed) for row in args.rows for seed in args.seeds]
    return score_runs(runs, args.out, Scoring.from_args(args))


def report(args: argparse.Namespace) -> int:
    scored = read_metrics(args.out, also=args.study)
    if scored is None:
        return 1
    rows, keys = scored
    print(f"# 9D ablation, {args.minutes:g} min of the quiet 2-core rate per run; mean over seeds (each seed)")
    entries = [([row], {run_dir(args, row, seed).name for seed in args.seeds}, []) for row in args.rows]
    print_seed_table(rows, keys, ["change"], entries)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser(__doc__.splitlines()[0], "runs/studies/9d-ablation")
    parser.add_argument("--study", type=Path, default=Path("runs/studies/9d-time"), help="the accuracy-vs-time study")
    parser.add_argument("--rows", type=lambda s: s.split(","), default=list(ROWS))
    parser.add_argument("--minutes", type=float, default=10.0)
    add_run_arguments(parser)
    args = parser.parse_args(argv)
    unknown = [r for r in args.rows if r not in ROWS]
    if unknown:
        parser.error(f"--rows: unknown {unknown}; known: {', '.join(ROWS)}")
    stage = {"train": train, "score": score, "report": report}[args.stage]
    return guarded(parser.prog, lambda: stage(args), catch_bugs=False)


if __name__ == "__main__":
    raise SystemExit(main())
