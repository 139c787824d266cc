"""The 9D layout study at a longer budget: the seed paper's six layouts, equal wall time each.

Run (resumable; every stage skips what is already done)::

    python benchmarks/nine_d_layouts.py train  --out runs/studies/9d-layouts
    python benchmarks/nine_d_layouts.py score  --out runs/studies/9d-layouts
    python benchmarks/nine_d_layouts.py report --out runs/studies/9d-layouts

The 3-minute layout study (docs/results/studies.md) ranks early training only. Here each of the paper's
six layouts (``--layouts``, default ssrsl, rsrsl, rrrsl, srrrl, ssssl, rrrrl) trains for
``--minutes`` (default 15) with the ``reach train`` defaults, for every seed in ``--seeds``, seed 0
of every layout first. As in the 9D accuracy-against-time study, minutes are trained as steps, so a
run trains the same steps whatever else shares its cores: ``minutes x
--steps-per-minute x`` the layout's speed relative to ``ssssl`` (:data:`RELATIVE_SPEED`; ReLU
layers are cheaper, and equal wall time is the comparison the paper's question asks for).
``--with ROW`` adds a change of the 9D ablation (``benchmarks/nine_d_ablation.py``,
:data:`studies.step_budget_study.CHANGES`, e.g. ``upper-bound``) to every run: the second half of
the study, the best recipe on the best layouts. ``score`` and ``report`` are the
accuracy-against-time study's (``reach evaluate`` with the same settings; mean and each seed per
layout, beside the seed paper's violation rates): the stages of :mod:`studies.step_budget_study`
and the tables of :mod:`studies.step_budget_report`, which every 9D study shares.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from reach_cli import guarded
from studies.step_budget_report import print_seed_table, read_metrics
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

#: the seed paper's six 9D layouts
PAPER_LAYOUTS = ("ssrsl", "rsrsl", "rrrsl", "srrrl", "ssssl", "rrrrl")

#: training steps per second relative to ssssl, 9D defaults, from steps 200-600 of ``reach --threads 2
#: train --system multivehicle9d --layout L --steps 600`` (measured: docs/results/studies.md)
RELATIVE_SPEED = {
    "ssssl": 1.0,
    "rsrsl": 10.79 / 10.06,
    "ssrsl": 10.67 / 10.06,
    "rrrsl": 13.03 / 10.06,
    "srrrl": 13.66 / 10.06,
    "rrrrl": 13.17 / 10.06,
}

#: the seed paper's 9D violation rates (%, 100k states, 150k GPU steps), ../shared/REFERENCE.md
PAPER_VIOLATION_PERCENT = {
    "ssrsl": 18.97,
    "rsrsl": 21.09,
    "rrrsl": 21.31,
    "srrrl": 27.15,
    "ssssl": 19.00,
    "rrrrl": 23.53,
}


def run_dir(args: argparse.Namespace, layout: str, seed: int) -> Path:
    change = "" if args.with_row == "baseline" else f"-{args.with_row}"
    return run_path(args.out, layout, args.minutes, seed, change)


def steps_for(args: argparse.Namespace, layout: str) -> int:
    return round(args.minutes * args.steps_per_minute * RELATIVE_SPEED[layout])


def train(args: argparse.Namespace) -> int:
    settings = change_settings(args.with_row, args.pairwise)
    runs = [  # every layout's seed 0 first: a partial study still ranks them all
        PlannedRun(run_dir(args, layout, seed), steps_for(args, layout), seed, {**settings, "layout": layout})
        for seed in args.seeds
        for layout in args.layouts
    ]
    return train_runs(runs, args.device)


def score(args: argparse.Namespace) -> int:
    runs = [run_dir(args, layout, seed) for seed in args.seeds for layout in args.layouts]
    return score_runs(runs, args.out, Scoring.from_args(args))


def report(args: argparse.Namespace) -> int:
    scored = read_metrics(args.out)
    if scored is None:
        return 1
    rows, keys = scored
    print(
        f"# 9D layouts, {args.minutes:g} min of the quiet 2-core rate per run"
        f"{'' if args.with_row == 'baseline' else ', with ' + args.with_row}; mean over seeds (each seed)"
    )
    entries = [
        (
            [layout, str(steps_for(args, layout))],
            {run_dir(args, layout, seed).name for seed in args.seeds},
            [str(PAPER_VIOLATION_PERCENT.get(layout, ""))],
        )
        for layout in args.layouts
    ]
    print_seed_table(rows, keys, ["layout", "steps"], entries, last=["paper violation %"])
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser(__doc__.splitlines()[0], "runs/studies/9d-layouts")
    parser.add_argument("--layouts", type=lambda s: s.split(","), default=list(PAPER_LAYOUTS))
    parser.add_argument("--minutes", type=float, default=15.0)
    parser.add_argument("--with", dest="with_row", default="baseline", help=f"an ablation change: {', '.join(CHANGES)}")
    add_run_arguments(parser)
    args = parser.parse_args(argv)
    unknown = [layout for layout in args.layouts if layout not in RELATIVE_SPEED]
    if unknown:
        parser.error(f"--layouts: no measured speed for {unknown}; measured: {', '.join(RELATIVE_SPEED)}")
    if args.with_row not in CHANGES:
        parser.error(f"--with: unknown change {args.with_row!r}; known: {', '.join(CHANGES)}")
    if not (args.minutes > 0):
        parser.error(f"--minutes must be > 0, got {args.minutes}")
    stage = {"train": train, "score": score, "report": report}[args.stage]
    return guarded(parser.prog, lambda: stage(args), catch_bugs=False)


if __name__ == "__main__":
    raise SystemExit(main())
