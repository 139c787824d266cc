"""The 9D layout study at a longer budget: the seed paper's six layouts, equal wall time each.

Run (resumable; every stage skips what is already done)::

    python benchmarks/nine_d_layouts.py train  --out runs/studies/9d-layouts
    python benchmarks/nine_d_layouts.py score  --out runs/studies/9d-layouts
    python benchmarks/nine_d_layouts.py report --out runs/studies/9d-layouts

The 3-minute layout study (docs/studies.md) ranks early training only. Here each of the paper's
six layouts (``--layouts``, default ssrsl, rsrsl, rrrsl, srrrl, ssssl, rrrrl) trains for
``--minutes`` (default 15) with the ``reach train`` defaults, for every seed in ``--seeds``, seed 0
of every layout first. As in the 9D accuracy-against-time study, minutes are trained as steps, so a
run sharing the cores with other work trains what a quiet machine trains in that time: ``minutes x
--steps-per-minute x`` the layout's speed relative to ``ssssl`` (:data:`RELATIVE_SPEED`; ReLU
layers are cheaper, and equal wall time is the comparison the paper's question asks for).
``--with ROW`` adds a change of the 9D ablation (``benchmarks/nine_d_ablation.py``, e.g.
``upper-bound``) to every run: the second half of the study, the best recipe on the best layouts.
``score`` and ``report`` are the accuracy-against-time study's (``reach evaluate`` with the same
settings; mean and each seed per layout, beside the seed paper's violation rates).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from nine_d_ablation import ROWS, ensure_pairwise_for
from nine_d_accuracy_vs_time import (
    add_run_arguments,
    evaluate_runs,
    read_metrics,
    seed_cells,
    train_or_resume,
)

#: the seed paper's six 9D layouts
PAPER_LAYOUTS = ("ssrsl", "rsrsl", "rrrsl", "srrrl", "ssssl", "rrrrl")

#: training steps per second relative to ssssl, 9D defaults, 2 threads, quiet 2-core machine
#: (AMD EPYC, AVX2): steps 200-600 of ``reach --threads 2 train --system multivehicle9d --layout L
#: --steps 600``, one layout after the other: ssssl 10.06, rsrsl 10.79, ssrsl 10.67, rrrsl 13.03,
#: srrrl 13.66, rrrrl 13.17 steps/s
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
    return args.out / "runs" / f"{layout}-{args.minutes:g}m{change}-seed{seed}"


def steps_for(args: argparse.Namespace, layout: str) -> int:
    return round(args.minutes * args.steps_per_minute * RELATIVE_SPEED[layout])


def train(args: argparse.Namespace) -> int:
    code = ensure_pairwise_for([args.with_row], Path(args.pairwise))
    if code:
        return code
    options = [option.format(pairwise=args.pairwise) for option in ROWS[args.with_row]]
    for seed in args.seeds:  # every layout's seed 0 first: a partial study still ranks them all
        for layout in args.layouts:
            run = run_dir(args, layout, seed)
            code = train_or_resume(run, steps_for(args, layout), seed, [*options, "--layout", layout], args.device)
            if code:
                return code
    return 0


def score(args: argparse.Namespace) -> int:
    return evaluate_runs([run_dir(args, layout, seed) for seed in args.seeds for layout in args.layouts], args)


def report(args: argparse.Namespace) -> int:
    scored = read_metrics(args.out)
    if scored is None:
        return 1
    rows, keys = scored
    print(
        f"# 9D layouts, {args.minutes:g} min of the quiet 2-core rate per run"
        f"{'' if args.with_row == 'baseline' else ', with ' + args.with_row}; mean over seeds (each seed)"
    )
    print("| layout | steps | seeds | " + " | ".join(keys) + " | paper violation % |")
    print("|---|---:|---:|" + "---:|" * len(keys) + "---:|")
    for layout in args.layouts:
        count, cells = seed_cells(rows, {run_dir(args, layout, seed).name for seed in args.seeds}, keys)
        if count:
            paper = PAPER_VIOLATION_PERCENT.get(layout, "")
            print(f"| {layout} | {steps_for(args, layout)} | {count} | " + " | ".join(cells) + f" | {paper} |")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["train", "score", "report"])
    parser.add_argument("--out", type=Path, default=Path("runs/studies/9d-layouts"))
    parser.add_argument("--layouts", type=lambda s: s.split(","), default=list(PAPER_LAYOUTS))
    parser.add_argument("--minutes", type=float, default=15.0)
    parser.add_argument("--with", dest="with_row", default="baseline", help=f"an ablation change: {', '.join(ROWS)}")
    add_run_arguments(parser)
    args = parser.parse_args(argv)
    unknown = [layout for layout in args.layouts if layout not in RELATIVE_SPEED]
    if unknown:
        parser.error(f"--layouts: no measured speed for {unknown}; measured: {', '.join(RELATIVE_SPEED)}")
    if args.with_row not in ROWS:
        parser.error(f"--with: unknown change {args.with_row!r}; known: {', '.join(ROWS)}")
    if not (args.minutes > 0):
        parser.error(f"--minutes must be > 0, got {args.minutes}")
    return {"train": train, "score": score, "report": report}[args.stage](args)


if __name__ == "__main__":
    raise SystemExit(main())
