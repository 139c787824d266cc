"""Result tables on disk: the same rows as JSON (with a header), CSV and markdown, each written atomically."""

from __future__ import annotations

import csv
import io
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from reach.atomic import atomic_path


def write_results(
    out: str | os.PathLike, header: dict[str, Any], rows: Sequence[dict[str, Any]], markdown: str
) -> None:
    """``out`` with suffixes ``.json`` (header + rows), ``.csv`` (flat columns) and ``.md``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out.with_suffix(".json")) as tmp, open(tmp, "w") as fh:
        json.dump({**header, "results": list(rows)}, fh, indent=2, sort_keys=True, default=str)
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
