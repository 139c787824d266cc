"""9D ablation: each change to the default recipe is one row, same seeds, same steps, scored the same way.

Run (resumable; every stage skips what is already done)::

    python benchmarks/nine_d_ablation.py train  --out runs/studies/9d-ablation
    python benchmarks/nine_d_ablation.py score  --out runs/studies/9d-ablation
    python benchmarks/nine_d_ablation.py report --out runs/studies/9d-ablation

Rows (``--rows``, default all): ``baseline`` (the defaults) and each change of :data:`ROWS`, trained
for ``--minutes`` of the quiet 2-core rate (as steps: ``minutes x --steps-per-minute``, so a run that
shares the cores trains what a quiet one trains in that time) for every seed in ``--seeds``. The
baseline reuses the 9D accuracy-against-time study's run of the same budget and seed where one
exists (``--study``; same command, same defaults), so the study and the ablation share their
baseline. ``score`` runs ``reach evaluate`` with the study's settings (``--samples`` uniform
states, ``--certify-samples`` fresh ones, the union of pairwise BRTs); ``report`` prints one row per
change, the mean over seeds and each seed's value.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from nine_d_accuracy_vs_time import (
    add_run_arguments,
    ensure_pairwise,
    evaluate_runs,
    read_metrics,
    seed_cells,
    train_or_resume,
)
from nine_d_accuracy_vs_time import run_dir as study_run_dir

#: the changes, each as the `reach train` options that make it (the baseline adds none)
ROWS: dict[str, list[str]] = {
    "baseline": [],
    # a known upper bound of the true value: V may not exceed the union of pairwise values
    "upper-bound": ["--upper-bound", "{pairwise}"],
    # a known lower bound: V may not sit below what the network's own policy achieves (rollout labels)
    "lower-bound": ["--lower-bound", "policy"],
    # DeepReach-MPC-style labels: the best of sampled control sequences, bootstrapped by the network
    "mpc-labels": ["--lower-bound", "mpc"],
    # both bounds: the union from above, the network's own policy from below
    "both-bounds": ["--upper-bound", "{pairwise}", "--lower-bound", "policy"],
    # a quarter of each step's points where the network's own |V| is smallest (of 4x as many draws)
    "zero-level": ["--zero-level-fraction", "0.25"],
    # the two terms that pushed towards soundness, without the labels that pulled the other way
    "upper-zero-level": ["--upper-bound", "{pairwise}", "--zero-level-fraction", "0.25"],
    # issue 18's candidate recipe: both bounds and the zero-level points together. Trained for 2 hours
    # of its own quiet rate (``--minutes 120 --steps-per-minute 433``: 400 steps took 55.4 s against
    # 38.4 s for the defaults, `reach --threads 2 train ... --steps 400`, nothing else running)
    "recipe": ["--upper-bound", "{pairwise}", "--lower-bound", "policy", "--zero-level-fraction", "0.25"],
}


def ensure_pairwise_for(rows: list[str], pairwise: Path) -> int:
    """Solve the pairwise grid ``pairwise`` first where one of ``rows`` trains against it (a run
    resumed on a fresh machine needs it as much as a new one). Returns the exit status (0: ready)."""
    if any("{pairwise}" in option for row in rows for option in ROWS[row]):
        return ensure_pairwise(pairwise)
    return 0


def run_dir(args: argparse.Namespace, row: str, seed: int) -> Path:
    """The run of a row and seed: the study's for the baseline where it exists, else the ablation's."""
    if row == "baseline":
        study = study_run_dir(args.study, args.minutes, seed)
        if (study / "checkpoint.pt").exists():
            return study
    return args.out / "runs" / f"{row}-{args.minutes:g}m-seed{seed}"


def train(args: argparse.Namespace) -> int:
    steps = round(args.minutes * args.steps_per_minute)
    code = ensure_pairwise_for(args.rows, Path(args.pairwise))
    if code:
        return code
    for row in args.rows:
        options = [option.format(pairwise=args.pairwise) for option in ROWS[row]]
        for seed in args.seeds:
            code = train_or_resume(run_dir(args, row, seed), steps, seed, options, args.device)
            if code:
                return code
    return 0


def score(args: argparse.Namespace) -> int:
    return evaluate_runs([run_dir(args, row, seed) for row in args.rows for seed in args.seeds], args)


def report(args: argparse.Namespace) -> int:
    scored = read_metrics(args.out, also=args.study)
    if scored is None:
        return 1
    rows, keys = scored
    print(f"# 9D ablation, {args.minutes:g} min of the quiet 2-core rate per run; mean over seeds (each seed)")
    print("| change | seeds | " + " | ".join(keys) + " |")
    print("|---|---:|" + "---:|" * len(keys))
    for row in args.rows:
        count, cells = seed_cells(rows, {run_dir(args, row, seed).name for seed in args.seeds}, keys)
        if count:
            print(f"| {row} | {count} | " + " | ".join(cells) + " |")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["train", "score", "report"])
    parser.add_argument("--out", type=Path, default=Path("runs/studies/9d-ablation"))
    parser.add_argument("--study", type=Path, default=Path("runs/studies/9d-time"), help="the accuracy-vs-time study")
    parser.add_argument("--rows", type=lambda s: s.split(","), default=list(ROWS))
    parser.add_argument("--minutes", type=float, default=10.0)
    add_run_arguments(parser)
    args = parser.parse_args(argv)
    unknown = [r for r in args.rows if r not in ROWS]
    if unknown:
        parser.error(f"--rows: unknown {unknown}; known: {', '.join(ROWS)}")
    return {"train": train, "score": score, "report": report}[args.stage](args)


if __name__ == "__main__":
    raise SystemExit(main())
