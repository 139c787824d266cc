"""The reports of a step-budget study (:mod:`studies.step_budget_study`): its scored table read back,
printed as Markdown and drawn against the training budget.

What: ``OUT/results.csv`` (``reach evaluate``'s table, one row per run, labelled by the run's folder
``<name>-<M>m-seed<S>``) becomes either one line per run (the accuracy-against-time table and plot,
:func:`print_table`, :func:`plot`) or one line per recipe or layout, each metric as the mean over
seeds with every seed's value beside it (:func:`seed_cells`, :func:`print_seed_table`).

Why apart from the training and scoring: a report needs neither torch nor the verification stack,
only the table, and each study's rows (its changes, its layouts) are the script's; this module holds
what the reports share, so that every study prints its metrics in the same columns and format.
"""

from __future__ import annotations

import csv
import json
import math
import re
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from reach.result_columns import current_names

#: the default recipe's runs (their layout); the accuracy-against-time table is of these
BASELINE = "ssssl"
#: the scored table in a study's folder
RESULTS = "results.csv"

#: the columns the reports print and plot, with their plot titles
METRICS = (
    ("violation_rate", "violation rate"),
    ("false_safe_rate", "false-safe rate"),
    ("collision_rate", "collision rate"),
    ("containment_miss_rate", "misses of the pairwise union"),
    ("scenario_volume", "delta-level scenario volume"),
    ("robust_scenario_volume", "robust scenario volume"),
)

#: issue 18's goals for a recipe of at most two CPU hours, drawn as dashed lines (rates as fractions)
GOALS = {
    "false_safe_rate": 0.0002,
    "collision_rate": 0.187,
    "containment_miss_rate": 0.0,
    "scenario_volume": 0.55,
    "robust_scenario_volume": 0.80,
}


def read_results(out: Path) -> list[dict[str, str]] | None:
    """The scored rows of ``out / results.csv``, error rows left out; None (and a message) where the
    score stage has not run yet."""
    path = out / RESULTS
    if not path.exists():
        print(f"{path}: run the score stage first", file=sys.stderr)
        return None
    with open(path) as fh:
        return [current_names(r) for r in csv.DictReader(fh) if not r.get("error")]


def scored_settings(out: Path) -> dict[str, Any] | None:
    """The verification settings ``out``'s table was scored with (``reach evaluate``'s results.json)."""
    path = (out / RESULTS).with_suffix(".json")
    return json.loads(path.read_text()).get("settings") if path.exists() else None


def read_metrics(out: Path, also: Path | None = None) -> tuple[list[dict[str, str]], list[str]] | None:
    """:func:`read_results` and the :data:`METRICS` keys its table has (None where not scored yet).
    ``also`` adds the rows of another study's table that this one's lacks (the ablation's baseline is
    the time study's run, scored there), where both tables were scored with the same settings."""
    rows = read_results(out)
    if rows is None:
        return None
    if also is not None and (also / RESULTS).exists():
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
    A value that is NaN (a scenario volume where no level could be bounded) shows as "none", and
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


def print_seed_table(
    rows: list[dict[str, str]],
    keys: list[str],
    first: Sequence[str],
    entries: Iterable[tuple[Sequence[str], set[str], Sequence[str]]],
    last: Sequence[str] = (),
) -> None:
    """A Markdown table of one line per entry that has a scored run: the columns ``first``, the
    number of seeds scored, a :func:`seed_cells` cell per metric of ``keys`` and the columns
    ``last``. Each entry is (its cells under ``first``, the labels of its runs, its cells under
    ``last``); the first column is left-aligned, every other one right-aligned."""
    print("| " + " | ".join([*first, "seeds"]) + " | " + " | ".join(keys) + " |" + "".join(f" {c} |" for c in last))
    print("|---|" + "---:|" * (len(first) + len(keys) + len(last)))
    for lead, labels, trail in entries:
        count, cells = seed_cells(rows, labels, keys)
        if count:
            head = " | ".join([*lead, str(count)])
            print(f"| {head} | " + " | ".join(cells) + " |" + "".join(f" {c} |" for c in trail))


def budget_and_seed(label: str, name: str = BASELINE) -> tuple[float, int] | None:
    """(minutes, seed) of a study run's label ``<name>-<M>m-seed<S>``; None for any other label."""
    m = re.fullmatch(rf"{re.escape(name)}-([0-9.]+)m-seed(\d+)", label)
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
    """Each metric against the training budget (minutes, log scale) of the default recipe's runs:
    one dot per seed, a line through the seeds' means, issue 18's goal as a dashed line."""
    # lazy: matplotlib only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the backend is chosen
    from matplotlib.ticker import NullFormatter  # lazy: with matplotlib

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
