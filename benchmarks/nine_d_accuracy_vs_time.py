"""9D (three cars) accuracy against training time: the default recipe at several budgets and seeds.

Run (resumable; every stage skips what is already done)::

    python benchmarks/nine_d_accuracy_vs_time.py train  --out runs/studies/9d-time
    python benchmarks/nine_d_accuracy_vs_time.py score  --out runs/studies/9d-time
    python benchmarks/nine_d_accuracy_vs_time.py report --out runs/studies/9d-time

``train`` trains what ``reach train --system multivehicle9d`` trains (the defaults), one run per
(budget, seed), in the order of the budgets (so short budgets finish first). A budget of M minutes
is trained as a fixed number of steps, ``M x --steps-per-minute``, instead of a wall-clock budget: a
run that shares the cores with other work (a background run beside a working session) then trains
exactly what a quiet machine trains in M minutes, and its schedule (cosine learning rate, time
curriculum) is the one an M-minute run has. ``--steps-per-minute`` defaults to the rate measured on
a quiet 2-core machine for the 9D default network (printed by the report with the rate each run
actually had). A killed run is resumed (as ``reach train --resume`` does), so stopping the script
loses at most one checkpoint interval.

``score`` verifies every finished run as ``reach evaluate`` does, with the same ``--samples``
uniform states and ``--scenario-samples`` fresh states, and the union of pairwise BRTs
(``--pairwise``, solved once as by ``reach groundtruth relativepair --grid 101`` if missing), into
one results table (rows merge, so scoring can be split across sessions). ``report`` prints the
markdown table and draws ``OUT/accuracy_vs_time.png``.

The stages are :mod:`studies.step_budget_study`'s and the table and plot
:mod:`studies.step_budget_report`'s; this script names the runs and parses the command line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from reach_cli import guarded
from studies.step_budget_report import BASELINE, plot, print_table, read_results
from studies.step_budget_study import (
    PlannedRun,
    Scoring,
    add_run_arguments,
    float_list,
    run_path,
    score_runs,
    stage_parser,
    train_runs,
)


def run_dir(out: Path, minutes: float, seed: int) -> Path:
    return run_path(out, BASELINE, minutes, seed)


def train(args: argparse.Namespace) -> int:
    steps = {minutes: round(minutes * args.steps_per_minute) for minutes in args.minutes}
    runs = [PlannedRun(run_dir(args.out, m, s), steps[m], s) for m in args.minutes for s in args.seeds]
    return train_runs(runs, args.device)


def score(args: argparse.Namespace) -> int:
    runs = [run_dir(args.out, m, s) for m in args.minutes for s in args.seeds]
    return score_runs(runs, args.out, Scoring.from_args(args))


def report(args: argparse.Namespace) -> int:
    rows = read_results(args.out)
    if rows is None:
        return 1
    print_table(rows)
    figure = plot(rows, args.out / "accuracy_vs_time.png")
    if figure is not None:
        print(f"\nwrote {figure}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser(__doc__.splitlines()[0], "runs/studies/9d-time")
    parser.add_argument("--minutes", type=float_list, default=[10, 30, 60, 120])
    add_run_arguments(parser)
    args = parser.parse_args(argv)
    stage = {"train": train, "score": score, "report": report}[args.stage]
    return guarded(parser.prog, lambda: stage(args), catch_bugs=False)


if __name__ == "__main__":
    raise SystemExit(main())
