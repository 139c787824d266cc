"""Result tables: the one markdown formatter, and the same rows on disk as JSON (with a header), CSV
and markdown, each written atomically.

A table is a sequence of columns ``(key, header, spec)``. ``spec`` is a format string
(``"{:.3f}"``), ``"pct"`` (a share printed in percent, two decimals) or ``"pct1"`` (one decimal), or
a callable ``(value, row) -> str`` for cells that need more of the row (a confidence interval).
Missing and NaN values print as ``-``; a row with an ``error`` spans the table with its message.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from reach.atomic import atomic_path
from reach.json_files import strict

Column = tuple[str, str, "str | Callable[[Any, dict[str, Any]], str]"]


def format_cell(value: Any, spec: str | Callable[[Any, dict[str, Any]], str], row: dict[str, Any]) -> str:
    """One cell by its column's ``spec`` (see the module docstring)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if callable(spec):
        return spec(value, row)
    if spec in ("pct", "pct1"):
        return f"{100 * value:.{2 if spec == 'pct' else 1}f}"
    return spec.format(value)


def escape_cell(text: str) -> str:
    """A cell's text with ``|`` escaped (``mean |u - u_nom|`` would otherwise split the cell, and the
    whole table renders as raw text)."""
    return str(text).replace("\\|", "|").replace("|", "\\|")


def render_markdown(headers: Sequence[str], cells: Sequence[Sequence[str]], align: str = "") -> str:
    """A markdown table from ready cells; ``align`` is one character a column (``l`` or ``r``, default ``l``)."""
    rule = "|" + "".join("---:|" if align[i : i + 1] == "r" else "---|" for i in range(len(headers)))
    lines = ["| " + " | ".join(map(escape_cell, headers)) + " |", rule]
    lines += ["| " + " | ".join(map(escape_cell, row)) + " |" for row in cells]
    return "\n".join(lines)


def columns_table(
    rows: Sequence[dict[str, Any]], columns: Sequence[Column], label_key: str = "label", drop_empty: bool = False
) -> str:
    """Rows as a markdown table of ``columns``; ``drop_empty`` leaves out columns no row has."""
    if drop_empty:
        columns = [c for c in columns if any(r.get(c[0]) is not None for r in rows)]
    cells = []
    for r in rows:
        if r.get("error"):
            error = r["error"] if len(r["error"]) <= 120 else r["error"][:117] + "..."
            cells.append([str(r.get(label_key, r.get("source", ""))), f"error: {error}", *[""] * (len(columns) - 2)])
            continue
        cells.append([format_cell(r.get(key), spec, r) for key, _, spec in columns])
    return render_markdown([header for _, header, _ in columns], cells)


def write_results(
    out: str | os.PathLike, header: dict[str, Any], rows: Sequence[dict[str, Any]], markdown: str
) -> None:
    """``out`` with suffixes ``.json`` (header + rows), ``.csv`` (flat columns) and ``.md``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out.with_suffix(".json")) as tmp, open(tmp, "w") as fh:
        # strict JSON: NaN metrics are written as null (read back as NaN by load_results)
        json.dump(strict({**header, "results": list(rows)}), fh, indent=2, sort_keys=True, default=str, allow_nan=False)
    keys: list[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys and not isinstance(r[k], (dict, list)))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=keys, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    with atomic_path(out.with_suffix(".csv")) as tmp:
        Path(tmp).write_text(buf.getvalue())
    with atomic_path(out.with_suffix(".md")) as tmp:
        Path(tmp).write_text(markdown + "\n")


def merge_rows(stored: Iterable[dict[str, Any]], new: Sequence[dict[str, Any]], key: str) -> list[dict[str, Any]]:
    """The rows of a table rerun in part: ``stored`` rows in their order, each replaced by the row of
    ``new`` with the same ``key`` (a rerun supersedes), then the ``new`` rows of keys not stored.
    ``reach evaluate`` (keyed by source) and ``reach filter-eval`` (by label) merge through it, each
    under its table's lock."""
    mine = {r[key]: r for r in new}
    return [mine.pop(r[key], r) for r in stored] + list(mine.values())
