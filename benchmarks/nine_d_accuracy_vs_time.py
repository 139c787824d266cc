"""9D (three cars) accuracy against training time: the default recipe at several budgets and seeds.

Run (resumable; every stage skips what is already done)::

    python benchmarks/nine_d_accuracy_vs_time.py train  --out studies/9d-time
    python benchmarks/nine_d_accuracy_vs_time.py score  --out studies/9d-time
    python benchmarks/nine_d_accuracy_vs_time.py report --out studies/9d-time

``train`` trains ``reach train --system multivehicle9d`` with the defaults, one run per
(budget, seed), in the order of the budgets (so short budgets finish first). A budget of M minutes
is trained as a fixed number of steps, ``M x --steps-per-minute``, instead of a wall-clock budget: a
run that shares the cores with other work (a background run beside a working session) then trains
exactly what a quiet machine trains in M minutes, and its schedule (cosine learning rate, time
curriculum) is the one an M-minute run has. ``--steps-per-minute`` defaults to the rate measured on
a quiet 2-core machine for the 9D default network (printed by the report with the rate each run
actually had). ``reach train --resume`` continues a killed run, so stopping the script loses at most
one checkpoint interval.

``score`` runs ``reach evaluate`` on every finished run with the same ``--samples`` uniform states
and ``--certify-samples`` fresh states, and the union of pairwise BRTs (``--pairwise``, solved once
by ``reach groundtruth relativepair`` if missing), into one results table (rows merge, so scoring
can be split across sessions). ``report`` prints the markdown table and draws
``OUT/accuracy_vs_time.png``.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from reach.cli import main as reach_main

#: 9D default network (ssssl, 4x128, 8192 points, compiled) on a quiet 2-core machine: 36,917 steps
#: in 40 minutes (the run that opened issue 18); minutes are converted to steps with this rate
QUIET_STEPS_PER_MINUTE = 923.0


def run_dir(out: Path, minutes: float, seed: int) -> Path:
    return out / "runs" / f"ssssl-{minutes:g}m-seed{seed}"


def train(args: argparse.Namespace) -> int:
    for minutes in args.minutes:
        for seed in args.seeds:
            run = run_dir(args.out, minutes, seed)
            steps = round(minutes * args.steps_per_minute)
            if (run / "checkpoint.pt").exists():
                code = reach_main(["train", "--resume", str(run), "--steps", str(steps)])
            else:
                code = reach_main(
                    [
                        "train",
                        "--system",
                        "multivehicle9d",
                        "--steps",
                        str(steps),
                        "--seed",
                        str(seed),
                        "--out",
                        str(run),
                    ]
                )
            if code:
                return code
    return 0


def score(args: argparse.Namespace) -> int:
    pairwise = Path(args.pairwise)
    if not pairwise.exists():
        code = reach_main(["groundtruth", "relativepair", "--grid", "101", "--out", str(pairwise)])
        if code:
            return code
    runs = [
        str(run_dir(args.out, m, s))
        for m in args.minutes
        for s in args.seeds
        if (run_dir(args.out, m, s) / "checkpoint.pt").exists()
    ]
    if not runs:
        print("no finished runs yet", file=sys.stderr)
        return 1
    return reach_main(
        [
            "evaluate",
            *runs,
            "--samples",
            str(args.samples),
            "--certify-samples",
            str(args.certify_samples),
            "--pairwise",
            str(pairwise),
            "--out",
            str(args.out / "results.csv"),
        ]
    )


def report(args: argparse.Namespace) -> int:
    path = args.out / "results.csv"
    if not path.exists():
        print(f"{path}: run the score stage first", file=sys.stderr)
        return 1
    with open(path) as fh:
        rows = [r for r in csv.DictReader(fh) if not r.get("error")]
    keys = ("violation_rate", "false_safe_rate", "collision_rate", "containment_miss_rate", "certified_volume")
    keys += ("robust_certified_volume",) if rows and "robust_certified_volume" in rows[0] else ()
    print("| run | steps | " + " | ".join(keys) + " |")
    print("|---|---:|" + "---:|" * len(keys))
    for r in rows:
        print(f"| {r['label']} | {r.get('steps', '')} | " + " | ".join(r.get(k, "") for k in keys) + " |")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["train", "score", "report"])
    parser.add_argument("--out", type=Path, default=Path("studies/9d-time"))
    parser.add_argument("--minutes", type=lambda s: [float(v) for v in s.split(",")], default=[10, 30, 60, 120])
    parser.add_argument("--seeds", type=lambda s: [int(v) for v in s.split(",")], default=[0, 1])
    parser.add_argument("--steps-per-minute", type=float, default=QUIET_STEPS_PER_MINUTE)
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--certify-samples", type=int, default=1_000_000)
    parser.add_argument("--pairwise", default="runs/pair_gt.npz")
    args = parser.parse_args(argv)
    return {"train": train, "score": score, "report": report}[args.stage](args)


if __name__ == "__main__":
    raise SystemExit(main())
