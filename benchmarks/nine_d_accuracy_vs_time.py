"""9D (three cars) accuracy against training time: the default recipe at several budgets and seeds.

Run (resumable; every stage skips what is already done)::

    python benchmarks/nine_d_accuracy_vs_time.py train  --out runs/studies/9d-time
    python benchmarks/nine_d_accuracy_vs_time.py score  --out runs/studies/9d-time
    python benchmarks/nine_d_accuracy_vs_time.py report --out runs/studies/9d-time

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
import json
import math
import re
import sys
from pathlib import Path

from reach.validation import device_arg, positive_int_arg
from reach_cli import main as reach_main

#: 9D default network (ssssl, 4x128, 8192 points, compiled) on a quiet 2-core machine: 36,917 steps
#: in 40 minutes (the run that opened issue 18); minutes are converted to steps with this rate
QUIET_STEPS_PER_MINUTE = 923.0


def run_dir(out: Path, minutes: float, seed: int) -> Path:
    return out / "runs" / f"ssssl-{minutes:g}m-seed{seed}"


def train_or_resume(run: Path, steps: int, seed: int, options: list[str] | None = None, device: str = "cpu") -> int:
    """``reach train`` of the 9D defaults (plus ``options``) for ``steps`` steps into ``run`` on
    ``device``, or ``--resume`` where a checkpoint is already there (on ``device``: a run may move
    between a CPU and a GPU; the step count, not the machine, fixes what it trains)."""
    if (run / "checkpoint.pt").exists():
        return reach_main(["train", "--resume", str(run), "--steps", str(steps), "--device", device])
    base = ["train", "--system", "multivehicle9d", "--steps", str(steps), "--seed", str(seed), "--device", device]
    return reach_main([*base, *(options or []), "--out", str(run)])


def train(args: argparse.Namespace) -> int:
    for minutes in args.minutes:
        for seed in args.seeds:
            steps = round(minutes * args.steps_per_minute)
            code = train_or_resume(run_dir(args.out, minutes, seed), steps, seed, device=args.device)
            if code:
                return code
    return 0


def finished(run: Path) -> bool:
    """Whether ``run`` reached the steps it was started for. A run stopped early (SIGTERM, a time
    limit) has a checkpoint too, and scoring it would put a half-trained network in the table."""
    record = run / "checkpoint.json"
    if not record.exists():
        return False
    meta = json.loads(record.read_text())
    target = meta.get("config", {}).get("steps")
    return target is None or int(meta.get("steps", 0)) >= int(target)


def ensure_pairwise(path: Path) -> int:
    """Solve the union of pairwise BRTs into ``path`` (``reach groundtruth relativepair --grid 101``)
    unless it is there: the scoring needs it, and so does every run trained with ``--upper-bound``,
    also when it resumes on a fresh machine. Returns the command's exit status (0 when present)."""
    if path.exists():
        return 0
    return reach_main(["groundtruth", "relativepair", "--grid", "101", "--out", str(path)])


def evaluate_runs(runs: list[Path], args: argparse.Namespace) -> int:
    """``reach evaluate`` of the runs that have a checkpoint, with the study's settings (solving the
    pairwise union first if missing), into ``args.out / results.csv``."""
    pairwise = Path(args.pairwise)
    code = ensure_pairwise(pairwise)
    if code:
        return code
    done = [str(run) for run in runs if finished(run)]
    if not done:
        print("no finished runs yet", file=sys.stderr)
        return 1
    samples = ["--samples", str(args.samples), "--certify-samples", str(args.certify_samples)]
    out = ["--pairwise", str(pairwise), "--out", str(args.out / "results.csv")]
    device = ["--device", args.device] + (["--chunk-size", str(args.chunk_size)] if args.chunk_size else [])
    return reach_main(["evaluate", *done, *samples, *device, *out])


def score(args: argparse.Namespace) -> int:
    return evaluate_runs([run_dir(args.out, m, s) for m in args.minutes for s in args.seeds], args)


#: the columns the report prints and plots, with their plot titles
METRICS = (
    ("violation_rate", "violation rate"),
    ("false_safe_rate", "false-safe rate"),
    ("collision_rate", "collision rate"),
    ("containment_miss_rate", "misses of the pairwise union"),
    ("certified_volume", "delta-level certified volume"),
    ("robust_certified_volume", "robust certified volume"),
)


#: issue 18's goals for a recipe of at most two CPU hours, drawn as dashed lines (rates as fractions)
GOALS = {
    "false_safe_rate": 0.0002,
    "collision_rate": 0.187,
    "containment_miss_rate": 0.0,
    "certified_volume": 0.55,
    "robust_certified_volume": 0.80,
}


def read_results(out: Path) -> list[dict[str, str]] | None:
    """The scored rows of ``out / results.csv``, error rows left out; None (and a message) where the
    score stage has not run yet."""
    path = out / "results.csv"
    if not path.exists():
        print(f"{path}: run the score stage first", file=sys.stderr)
        return None
    with open(path) as fh:
        return [r for r in csv.DictReader(fh) if not r.get("error")]


def scored_settings(out: Path) -> dict | None:
    """The verification settings ``out``'s table was scored with (``reach evaluate``'s results.json)."""
    path = out / "results.json"
    return json.loads(path.read_text()).get("settings") if path.exists() else None


def read_metrics(out: Path, also: Path | None = None) -> tuple[list[dict[str, str]], list[str]] | None:
    """:func:`read_results` and the :data:`METRICS` keys its table has (None where not scored yet).
    ``also`` adds the rows of another study's table that this one's lacks (the ablation's baseline is
    the time study's run, scored there), where both tables were scored with the same settings."""
    rows = read_results(out)
    if rows is None:
        return None
    if also is not None and (also / "results.csv").exists():
        settings = [scored_settings(d) for d in (out, also)]
        if settings[0] is not None and settings[0] == settings[1]:
            labels = {r["label"] for r in rows}
            rows += [r for r in read_results(also) or [] if r["label"] not in labels]
        else:
            print(f"{also}: scored with other settings than {out}; its rows are left out", file=sys.stderr)
    return rows, [k for k, _ in METRICS if rows and k in rows[0]]


def seed_cells(rows: list[dict[str, str]], labels: set[str], keys: list[str]) -> tuple[int, list[str]]:
    """How many of ``rows`` carry one of ``labels`` (runs are labelled by their folder), and per
    metric in ``keys`` a cell "mean (each seed's value)": one row of the ablation and layout reports.
    A value that is NaN (a certified volume where no level could be certified) shows as "none", and
    the mean is then left out ("-"): averaging it away would flatter the row."""
    scored = sorted((r for r in rows if r["label"] in labels), key=lambda r: r["label"])
    cells = []
    for key in keys:
        values = [float(r[key]) for r in scored if r.get(key) not in (None, "")]
        each = ", ".join("none" if math.isnan(v) else f"{v:.4g}" for v in values)
        if not values:
            cells.append("-")
        elif any(math.isnan(v) for v in values):
            cells.append(f"- ({each})")
        else:
            cells.append(f"{sum(values) / len(values):.4g} ({each})")
    return len(scored), cells


def budget_and_seed(label: str) -> tuple[float, int] | None:
    """(minutes, seed) of a study run's label ``ssssl-<M>m-seed<S>``; None for any other label."""
    m = re.fullmatch(r"ssssl-([0-9.]+)m-seed(\d+)", label)
    return (float(m.group(1)), int(m.group(2))) if m else None


def print_table(rows: list[dict[str, str]]) -> None:
    """The scored runs as a markdown table, shortest budget first."""
    rows = sorted(rows, key=lambda r: budget_and_seed(r["label"]) or (math.inf, 0))
    keys = [k for k, _ in METRICS if rows and k in rows[0]]
    print("| run | " + " | ".join(keys) + " |")
    print("|---|" + "---:|" * len(keys))
    for r in rows:
        print(f"| {r['label']} | " + " | ".join(r.get(k, "") for k in keys) + " |")


def plot(rows: list[dict[str, str]], path: Path) -> Path | None:
    """Each metric against the training budget (minutes, log scale): one dot per seed, a line
    through the seeds' means."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    points = [(found[0], r) for r in rows if (found := budget_and_seed(r["label"])) is not None]
    if not points:
        return None
    keys = [(k, title) for k, title in METRICS if k in points[0][1]]
    fig, axes = plt.subplots(2, (len(keys) + 1) // 2, figsize=(4 * ((len(keys) + 1) // 2), 6.5), squeeze=False)
    for ax, (key, title) in zip(axes.flat, keys):
        xs = [m for m, r in points if r.get(key) not in (None, "")]
        ys = [float(r[key]) for m, r in points if r.get(key) not in (None, "")]
        ax.plot(xs, ys, "o", alpha=0.6)
        budgets = sorted(set(xs))
        ax.plot(budgets, [sum(y for x, y in zip(xs, ys) if x == b) / xs.count(b) for b in budgets], "-")
        ax.set_xscale("log")
        ax.set_xticks(budgets, [f"{b:g}" for b in budgets])
        ax.xaxis.set_minor_formatter(NullFormatter())
        if key in GOALS:
            ax.axhline(GOALS[key], color="grey", linestyle="--", linewidth=1, label="issue 18 goal")
            ax.legend(fontsize="small")
        ax.set_title(title)
        ax.set_xlabel("budget: steps of M quiet 2-core CPU minutes")
    for ax in list(axes.flat)[len(keys) :]:
        ax.axis("off")
    fig.suptitle("9D default recipe: accuracy against training time (one dot per seed)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def report(args: argparse.Namespace) -> int:
    rows = read_results(args.out)
    if rows is None:
        return 1
    print_table(rows)
    figure = plot(rows, args.out / "accuracy_vs_time.png")
    if figure is not None:
        print(f"\nwrote {figure}")
    return 0


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """The seeds, the step rate and the scoring settings: one source for the study and the ablation,
    so that both train and score their runs the same way."""
    parser.add_argument("--seeds", type=lambda s: [int(v) for v in s.split(",")], default=[0, 1])
    parser.add_argument("--steps-per-minute", type=float, default=QUIET_STEPS_PER_MINUTE)
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--certify-samples", type=int, default=1_000_000)
    parser.add_argument("--pairwise", default="runs/pair_gt.npz")
    parser.add_argument("--device", type=device_arg, default="cpu", help="train and score on this device (cpu or cuda)")
    parser.add_argument(
        "--chunk-size",
        type=positive_int_arg,
        default=None,
        help="states per batch when scoring (reach evaluate's default; on a GPU 262144 avoids being launch-bound)",
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["train", "score", "report"])
    parser.add_argument("--out", type=Path, default=Path("runs/studies/9d-time"))
    parser.add_argument("--minutes", type=lambda s: [float(v) for v in s.split(",")], default=[10, 30, 60, 120])
    add_run_arguments(parser)
    args = parser.parse_args(argv)
    return {"train": train, "score": score, "report": report}[args.stage](args)


if __name__ == "__main__":
    raise SystemExit(main())
