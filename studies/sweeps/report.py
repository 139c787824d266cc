"""A sweep's report: per-layout summaries over seeds, the Pareto plot, and checks of the paper's claims.

Everything here reads the rows of :func:`studies.sweeps.task.run_task` (one per layout, seed and snapshot)
and computes; nothing trains or evaluates, so a report can be redrawn from ``results.json`` alone.
"""

from __future__ import annotations

import itertools
import math
import os
import statistics
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from studies.tables import format_cell, render_markdown

Row = dict[str, Any]

#: how each metric is written in tables (header, format; "pct" prints a percentage)
METRIC_FORMATS: dict[str, tuple[str, str]] = {
    "iou_volume": ("IoU vol.", "{:.3f}"),
    "mse_volume": ("MSE vol.", "{:.2e}"),
    "iou_slice": ("IoU slice", "{:.3f}"),
    "mse_slice": ("MSE slice", "{:.2e}"),
    "violation_rate": ("violation %", "pct"),
    "delta": ("delta", "{:.3f}"),
    "scenario_volume": ("scenario vol.", "{:.3f}"),
    "collision_rate": ("collision %", "pct"),
    "containment_miss_rate": ("misses union %", "pct"),
}


def _fmt(value: float, spec: str) -> str:
    return format_cell(value, spec, {})


def _finite(values: Sequence[Any]) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(float(v))]


def spread(values: Sequence[Any]) -> dict[str, float]:
    """Mean, sample standard deviation (0 for one value), min and max of the finite values."""
    v = _finite(values)
    if not v:
        return {"mean": math.nan, "std": math.nan, "min": math.nan, "max": math.nan, "n": 0}
    return {
        "mean": statistics.fmean(v),
        "std": statistics.stdev(v) if len(v) > 1 else 0.0,
        "min": min(v),
        "max": max(v),
        "n": len(v),
    }


def curves(rows: Sequence[Row], metric: str) -> dict[str, list[dict[str, float]]]:
    """Per layout, per snapshot: the seeds' mean training time and the metric's spread."""
    groups: dict[str, dict[int, list[Row]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        groups[r["layout"]][r["snapshot"]].append(r)
    out: dict[str, list[dict[str, float]]] = {}
    for layout, by_snap in groups.items():
        out[layout] = [
            {"snapshot": k, "wall": statistics.fmean(r["wall"] for r in rs), **spread([r.get(metric) for r in rs])}
            for k, rs in sorted(by_snap.items())
        ]
    return out


def final_rows(rows: Sequence[Row]) -> dict[str, list[Row]]:
    """Per layout, the last evaluated snapshot of each seed."""
    last: dict[tuple[str, int], Row] = {}
    for r in rows:
        key = (r["layout"], r["seed"])
        if key not in last or r["snapshot"] > last[key]["snapshot"]:
            last[key] = r
    out: dict[str, list[Row]] = defaultdict(list)
    for (layout, _), r in sorted(last.items(), key=lambda kv: kv[0]):
        out[layout].append(r)
    return dict(out)


def rank_layouts(rows: Sequence[Row], metric: str, higher_is_better: bool) -> list[tuple[str, float]]:
    """Layouts by the seeds' mean final ``metric``, best first."""
    means = [(layout, spread([r.get(metric) for r in rs])["mean"]) for layout, rs in final_rows(rows).items()]
    means = [(k, m) for k, m in means if not math.isnan(m)]
    return sorted(means, key=lambda km: -km[1] if higher_is_better else km[1])


def summary_table(rows: Sequence[Row], headline: Sequence[tuple[str, bool]]) -> str:
    """Markdown: per layout (best first), final metrics as mean ± std over seeds, steps and steps/s."""
    finals = final_rows(rows)
    ranked = [k for k, _ in rank_layouts(rows, *headline[0])]
    order = ranked + [k for k in finals if k not in ranked]
    metrics = [m for m, _ in headline]
    head = ["layout", "seeds", *(METRIC_FORMATS.get(m, (m, "{:.3g}"))[0] for m in metrics), "steps", "steps/s"]
    table = []
    for layout in order:
        rs = finals[layout]
        cells = [f"`{layout}`", str(len(rs))]
        for m in metrics:
            s = spread([r.get(m) for r in rs])
            spec = METRIC_FORMATS.get(m, (m, "{:.3g}"))[1]
            cells.append(f"{_fmt(s['mean'], spec)} ± {_fmt(s['std'], spec)}" if s["n"] > 1 else _fmt(s["mean"], spec))
        cells.append(f"{statistics.fmean(r['step'] for r in rs):.0f}")
        cells.append(f"{statistics.fmean(r['steps_per_s'] for r in rs):.1f}")
        table.append(cells)
    return render_markdown(head, table, "l" + "r" * (len(head) - 1))


def pareto_front(points: Sequence[tuple[float, float, str]], higher_is_better: bool) -> list[tuple[float, float, str]]:
    """The (time, score, label) points no other point beats on both time and score, by time."""
    front: list[tuple[float, float, str]] = []
    best = -math.inf
    for t, score, label in sorted(points, key=lambda p: (p[0], -p[1] if higher_is_better else p[1])):
        s = score if higher_is_better else -score
        if math.isfinite(s) and s > best:
            front.append((t, score, label))
            best = s
    return front


def plot_pareto(
    rows: Sequence[Row], path: str | os.PathLike, headline: Sequence[tuple[str, bool]], title: str = ""
) -> Path:
    """One panel per headline metric: each layout's mean over seeds against training time, the seeds'
    min-max band shaded, and the Pareto front over all (layout, snapshot) means as a dashed line."""
    # lazy: matplotlib only when drawing
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    metrics = list(headline[:2])
    fig = Figure(figsize=(5.2 * len(metrics), 4.0), dpi=100)
    FigureCanvasAgg(fig)
    for i, (metric, higher) in enumerate(metrics):
        ax = fig.add_subplot(1, len(metrics), i + 1)
        scale = 100.0 if METRIC_FORMATS.get(metric, ("", ""))[1] == "pct" else 1.0  # rates drawn in percent
        points = []
        for k, (layout, pts) in enumerate(sorted(curves(rows, metric).items())):
            pts = [p for p in pts if p["n"]]
            if not pts:
                continue
            wall = [p["wall"] for p in pts]
            colour = f"C{k % 10}"
            ax.plot(wall, [scale * p["mean"] for p in pts], "o-", ms=3, color=colour, label=layout)
            lo, hi = [scale * p["min"] for p in pts], [scale * p["max"] for p in pts]
            ax.fill_between(wall, lo, hi, color=colour, alpha=0.15)
            points += [(p["wall"], scale * p["mean"], layout) for p in pts]
        front = pareto_front(points, higher)
        if front:  # drawn on to the latest time: nothing later beats the front's last point
            xs = [p[0] for p in front] + [max(p[0] for p in points)]
            ys = [p[1] for p in front] + [front[-1][1]]
            ax.step(xs, ys, "k--", where="post", lw=1, label="Pareto front")
        if metric.startswith("mse"):
            ax.set_yscale("log")
        ax.set_xlabel("training wall time (s)")
        ax.set_ylabel(f"{METRIC_FORMATS.get(metric, (metric,))[0]} ({'higher' if higher else 'lower'} is better)")
        ax.grid(alpha=0.3)
        if i == 0:
            ax.legend(fontsize=7, ncol=2)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    return path


def _spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman rank correlation (average ranks for ties); NaN with fewer than 3 points or no spread."""
    if len(x) < 3:
        return math.nan
    rx, ry = _ranks(x), _ranks(y)
    mx, my = statistics.fmean(rx), statistics.fmean(ry)
    sx = math.sqrt(sum((a - mx) ** 2 for a in rx))
    sy = math.sqrt(sum((b - my) ** 2 for b in ry))
    if sx == 0 or sy == 0:
        return math.nan
    return sum((a - mx) * (b - my) for a, b in zip(rx, ry)) / (sx * sy)


def _ranks(values: Sequence[float]) -> list[float]:
    """Ranks from 0, ties sharing their average rank."""
    order = sorted(range(len(values)), key=lambda i: values[i])
    r = [0.0] * len(values)
    i = 0
    while i < len(order):
        j = i
        while j + 1 < len(order) and values[order[j + 1]] == values[order[i]]:
            j += 1
        for k in range(i, j + 1):
            r[order[k]] = (i + j) / 2
        i = j + 1
    return r


def spearman_permutation_p(x: Sequence[float], y: Sequence[float], max_exact: int = 9, draws: int = 100_000) -> float:
    """One-sided p-value of Spearman's rho being at least the observed one if ``y`` were unrelated to
    ``x``: exact over all orderings of ``y`` for up to ``max_exact`` points, else from ``draws``
    seeded random orderings. NaN below 3 points."""
    n = len(x)
    if n < 3:
        return math.nan
    rx = np.asarray(_ranks(x), dtype=float)
    ry = np.asarray(_ranks(y), dtype=float)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denom = math.sqrt(float((rx**2).sum()) * float((ry**2).sum()))
    if denom == 0:
        return math.nan
    observed = float(rx @ ry) / denom
    if n <= max_exact:
        perms = np.array(list(itertools.permutations(range(n))), dtype=np.int64)
    else:
        rng = np.random.default_rng(0)
        perms = np.argsort(rng.random((draws, n)), axis=1)
    stats = ry[perms] @ rx / denom
    return float((stats >= observed - 1e-12).mean())


def _subset_permutation_p(scores: Sequence[float], chosen: Sequence[bool]) -> float:
    """One-sided p-value of the chosen layouts' mean minus the rest's being at least the observed
    gap if the chosen ones were any layouts of the same count (exact, over all subsets)."""
    n, k = len(scores), sum(chosen)
    if k == 0 or k == n:
        return math.nan
    total = sum(scores)

    def gap(idx: Sequence[int]) -> float:
        a = sum(scores[i] for i in idx)
        return a / k - (total - a) / (n - k)

    observed = gap([i for i, c in enumerate(chosen) if c])
    gaps = [gap(idx) for idx in itertools.combinations(range(n), k)]
    return sum(g >= observed - 1e-12 for g in gaps) / len(gaps)


def claims(rows: Sequence[Row], metric: str, higher_is_better: bool) -> list[dict[str, Any]]:
    """Numbers behind the seed paper's two claims, on the final ``metric`` (seed means per layout).

    1. "more sine layers are better": Spearman correlation between a layout's number of sine
       layers and its score (sign-adjusted so that > 0 supports the claim), with the one-sided
       permutation p-value over the layouts;
    2. "sine on the first and last hidden layer matters most": mean score of layouts with sine in
       both places minus that of the others (sign-adjusted), with the one-sided p-value of that gap
       over all ways of picking as many layouts, and the mean seed-to-seed spread for scale.
    """
    finals = final_rows(rows)
    sign = 1.0 if higher_is_better else -1.0
    layouts, scores, spreads = [], [], []
    for layout, rs in finals.items():
        s = spread([r.get(metric) for r in rs])
        if s["n"]:
            layouts.append(layout)
            scores.append(sign * s["mean"])  # sign-adjusted: larger is better from here on
            spreads.append(s["std"])
    hidden = [layout[:-1] for layout in layouts]
    sines = [h.count("s") for h in hidden]
    ends = [h[0] == "s" and h[-1] == "s" for h in hidden]
    with_ends = [s for s, e in zip(scores, ends) if e]
    without = [s for s, e in zip(scores, ends) if not e]
    gap = statistics.fmean(with_ends) - statistics.fmean(without) if with_ends and without else math.nan
    return [
        {
            "claim": "more sine layers are better",
            "statistic": f"Spearman rho (sine layers, score) over {len(layouts)} layouts",
            "value": _spearman(sines, scores),
            "p_value": spearman_permutation_p(sines, scores),
            "layouts": len(layouts),
        },
        {
            "claim": "sine on the first and last hidden layer matters most",
            "statistic": f"mean score with sine at both ends minus without ({len(with_ends)} vs {len(without)})",
            "value": gap,
            "p_value": _subset_permutation_p(scores, ends),
            "seed_std": statistics.fmean(spreads) if spreads else math.nan,
        },
    ]


def claims_table(rows: Sequence[Row], headline: Sequence[tuple[str, bool]]) -> str:
    """Markdown: the claims' statistics on each headline metric (sign-adjusted: > 0 agrees with the
    claim), their one-sided permutation p-values, and the mean seed-to-seed spread."""
    head = ["metric", "claim", "statistic (> 0 agrees)", "value", "one-sided p", "mean seed std"]
    table = []
    for metric, higher in headline:
        for c in claims(rows, metric, higher):
            std = c.get("seed_std")
            table.append(
                [
                    metric,
                    c["claim"],
                    c["statistic"],
                    _fmt(c["value"], "{:.3g}"),
                    _fmt(c["p_value"], "{:.3f}"),
                    _fmt(std, "{:.3g}") if std is not None else "",
                ]
            )
    return render_markdown(head, table, "lllrrr")
