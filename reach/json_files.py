"""Reading the project's JSON files: one reader that refuses what it cannot trust, naming the file.

Results tables, sweep specs, model cards and run metadata are JSON objects, most with a ``format``
tag that says which kind of file they are. :func:`read_json` reads one as a regular file only (a
FIFO would block, a device would never end), parses it, checks it is an object and, where asked,
its tag, and turns every failure into one ``ValueError`` that names the file and says what to do.
Writes go through :func:`reach.atomic.atomic_path`, and :func:`strict` makes data strict JSON: a
metric that is not defined (NaN) or infinite is written as ``null``, never as the ``NaN`` literal
that strict readers (``jq``, JavaScript, most languages' parsers) reject; :func:`restore_nan` reads
such a ``null`` back as NaN where the column holds numbers.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import Any

from reach.validation import file_kind


def read_json(path: str | os.PathLike, what: str, expect_format: str | None = None, hint: str = "") -> dict[str, Any]:
    """The JSON object in ``path``, a ``what`` (e.g. ``"evaluation results"``).

    Raises ``ValueError`` naming ``path`` when it is missing, not a regular file, unreadable, not
    JSON, not an object, or (given ``expect_format``) tagged with another ``"format"``. ``hint`` is
    appended to the message (for example "; move the file away to start over").
    """
    p = Path(path)
    try:
        mode = p.stat().st_mode
    except OSError as err:
        raise ValueError(f"{p}: {what} is unreadable ({err.strerror or err}){hint}") from err
    if not stat.S_ISREG(mode):
        raise ValueError(f"{p}: {what} must be a regular file, not a {file_kind(mode)}{hint}")
    try:
        data = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{p}: {what} is corrupt or unreadable ({err}){hint}") from err
    if not isinstance(data, dict):
        raise ValueError(f"{p}: not {what} (a JSON object expected, got {type(data).__name__}){hint}")
    if expect_format is not None and data.get("format") != expect_format:
        raise ValueError(f"{p}: not {what} (format {expect_format!r} expected, got {data.get('format')!r}){hint}")
    return data


def strict(data: Any) -> Any:
    """``data`` with every non-finite float (NaN, inf) replaced by ``None``, recursively through
    dicts, lists and tuples, so that ``json.dump(..., allow_nan=False)`` accepts it."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {key: strict(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [strict(value) for value in data]
    return data


def restore_nan(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows read back from a strict-JSON table, with ``None`` read as NaN in every column that holds
    a float in some row (the inverse of :func:`strict` for tables of metrics)."""
    numeric = {key for row in rows for key, value in row.items() if isinstance(value, float)}
    return [{k: math.nan if v is None and k in numeric else v for k, v in row.items()} for row in rows]


__all__ = ["read_json", "restore_nan", "strict"]
