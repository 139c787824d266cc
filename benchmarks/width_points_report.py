"""Report of ``benchmarks/gpu_width_points.sh``: one row per trained variant, from its run's files.

Run, on the folders the GPU script's ``runs.tgz`` unpacks into (each holds ``w*-p*`` run
directories and the ``eval-w*-p*.json`` that ``reach evaluate`` wrote for them)::

    python benchmarks/width_points_report.py runs/width-points/a runs/width-points/b \\
        --json docs/studies/width_points_15d.json --plot docs/width_points_15d.png

For each run: its width and points per step, its wall budget, the steps it trained and its last
logged rate and loss terms (``metrics.jsonl``), and the card protocol's figures (false safe, false
unsafe, delta-level volume and eps, misses of the pairwise union). Prints a Markdown table; writes
the rows as JSON and a plot of the false-safe rate against training seconds, one marker per width.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from reach.atomic import atomic_path

#: the evaluation figures each row keeps (``reach evaluate``'s column names)
EVALUATION_KEYS = (
    "samples",
    "violation_rate",
    "false_safe_rate",
    "false_unsafe_rate",
    "collision_rate",
    "delta",
    "eps",
    "scenario_states",
    "scenario_failures",
    "scenario_volume",
    "scenario_error",
    "robust_error",
    "containment_miss_rate",
    "union_fraction",
    "wall_time",
)


def read_run(folder: Path, run: Path) -> dict[str, Any]:
    """One variant's row from its run directory ``run`` and its evaluation ``folder/eval-NAME.json``;
    a missing or malformed file stops with its path."""
    try:
        checkpoint = json.loads((run / "checkpoint.json").read_text())
        last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
        evaluation = json.loads((folder / f"eval-{run.name}.json").read_text())
        (row,) = evaluation["results"]
    except (OSError, ValueError, KeyError, IndexError) as err:
        raise SystemExit(f"{run}: not a scored run of gpu_width_points.sh ({type(err).__name__}: {err})") from err
    config = checkpoint["config"]
    return {
        "variant": run.name,
        "system": config["system"],
        "width": checkpoint["width"],
        "points": config["points"],
        "budget_s": config["budget_s"],
        "steps": checkpoint["steps"],
        "training_s": round(checkpoint["wall_time_s"], 1),
        "last_logged": {k: last.get(k) for k in ("steps_per_s", "loss", "pde", "upper_bound")},
        "evaluation": {k: row[k] for k in EVALUATION_KEYS if k in row},
        "evaluation_settings": evaluation["settings"],
    }


def collect(folders: list[Path]) -> list[dict[str, Any]]:
    """Every scored run in ``folders``, in order of folder, then budget, then width."""
    rows = []
    for folder in folders:
        runs = sorted(p for p in folder.glob("w*-p*") if p.is_dir())
        if not runs:
            raise SystemExit(f"{folder}: no run directories (w*-p*) of gpu_width_points.sh")
        rows += sorted((read_run(folder, r) for r in runs), key=lambda r: (r["budget_s"], r["width"]))
    return rows


def _percent(value: Any) -> str:
    return "-" if value is None else f"{100 * value:.2f}"


def table(rows: list[dict[str, Any]]) -> str:
    """The rows as a Markdown table."""
    lines = [
        "| width | points | budget (s) | steps | steps/s (last) | loss / pde | false safe % | false unsafe % "
        "| delta-level vol. [eps] | misses of the union % |",
        "|---:|---:|---:|---:|---:|---|---:|---:|---|---:|",
    ]
    for r in rows:
        e, last = r["evaluation"], r["last_logged"]
        volume = "none" if e.get("scenario_volume") is None else f"{e['scenario_volume']:.3f} [{e['eps']:.1e}]"
        lines.append(
            f"| {r['width']} | {r['points']:,} | {r['budget_s']:g} | {r['steps']:,} | {last['steps_per_s']:.0f} "
            f"| {last['loss']:.4f} / {last['pde']:.4f} | {_percent(e.get('false_safe_rate'))} "
            f"| {_percent(e.get('false_unsafe_rate'))} | {volume} | {_percent(e.get('containment_miss_rate'))} |"
        )
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """False-safe rate against training seconds, one marker per width, with the 0.05 % goal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for width in sorted({r["width"] for r in rows}):
        mine = [r for r in rows if r["width"] == width]
        ax.plot(
            [r["training_s"] for r in mine],
            [100 * r["evaluation"]["false_safe_rate"] for r in mine],
            "o",
            label=f"width {width}, {mine[0]['points']:,} points a step",
        )
    ax.axhline(0.05, color="k", linestyle="--", linewidth=1, label="goal: 0.05 %")
    ax.set_yscale("log")
    ax.set_xlabel("training seconds on the GPU")
    ax.set_ylabel("false safe % (100,000 states)")
    ax.set_title(f"{rows[0]['system']}: width and points at an equal GPU budget")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="folders of unpacked runs.tgz")
    parser.add_argument("--json", type=Path, default=None, help="write the rows here")
    parser.add_argument("--plot", type=Path, default=None, help="write the plot here (.png)")
    parser.add_argument("--hardware", default="", help="where the runs trained and were scored (kept in the JSON)")
    args = parser.parse_args(argv)
    rows = collect(args.folders)
    print(table(rows))
    if args.json is not None:
        data = {"command": "benchmarks/gpu_width_points.sh", "hardware": args.hardware, "runs": rows}
        with atomic_path(args.json) as tmp:
            Path(tmp).write_text(json.dumps(data, indent=1) + "\n")
    if args.plot is not None:
        plot(rows, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
