"""Filter-study rows as tables and results files: labels, the Markdown table, writing and merging.

Why apart from the episodes: a table outlives one invocation. ``reach filter-eval`` runs into the
same ``--out`` add their rows to one table (:func:`merge_filter_results`), so reading, checking and
merging results must work without running anything, and before any episode runs
(:func:`filter_table_rows`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from reach.json_files import read_json, restore_nan
from reach.locking import exclusive_lock
from reach.result_columns import current_names
from studies.filter_configs import FilterConfig
from studies.tables import columns_table, merge_rows, write_results


def backup_horizon_of(config: FilterConfig) -> float:
    """The lookahead's backup rollout in seconds, its default (the system's horizon) resolved."""
    horizon = config.settings.backup_horizon
    return config.value_function.system.horizon if horizon is None else float(horizon)


def labelled(row: dict[str, Any]) -> dict[str, Any]:
    """``value_function`` = the configuration's name; ``label`` adds the threshold when filtered."""
    name = row["label"]
    threshold = row["threshold"]
    if threshold is None:
        return {**row, "value_function": name, "label": name}
    kind = "" if row.get("kind") in (None, "switch") else f" {row['kind']}"
    gamma = f" g{row['gamma']:g}" if row.get("gamma") is not None else ""
    policy = " greedy" if row.get("policy") == "greedy" else ""
    return {**row, "value_function": name, "label": f"{name}{kind}{policy} @ {threshold:.3g}{gamma}"}


def settings_columns(config: FilterConfig) -> dict[str, Any]:
    """The row's columns that say which filter ran (``None`` where a setting does not apply)."""
    s = config.settings
    filtered = config.value_function is not None
    lookahead = filtered and s.kind == "lookahead"
    return {
        "kind": s.kind if filtered else None,
        "gamma": s.gamma if filtered and s.kind == "smooth" else None,
        "backup_horizon": backup_horizon_of(config) if lookahead else None,
        "backup_disturbance": s.backup_disturbance if lookahead else None,
        "policy": s.backup_policy if filtered else None,
    }


def _with_interval(value: float, row: dict[str, Any]) -> str:
    """A collision rate with its 95 % Wilson interval, in percent."""
    return f"{100 * value:.2f} [{100 * row['collision_ci_low']:.2f}, {100 * row['collision_ci_high']:.2f}]"


FILTER_COLUMNS = (
    ("label", "configuration", "{}"),
    ("threshold", "threshold", "{:.3g}"),
    ("collision_rate", "collision % [95 % CI]", _with_interval),
    ("intervention_rate", "intervention %", "pct1"),
    ("mean_input_change", "mean |u - u_nom|", "{:.3f}"),
    ("total_variation", "input TV", "{:.2f}"),
    ("min_margin", "min l", "{:.3f}"),
    ("goal_rate", "goal %", "pct1"),
    ("mean_goal_time", "goal time (s)", "{:.2f}"),
    ("wall_time", "wall (s)", "{:.1f}"),
)


def filter_table(rows: Sequence[dict[str, Any]]) -> str:
    """The markdown table of :func:`~studies.filter_episodes.evaluate_filters` rows."""
    return columns_table(rows, FILTER_COLUMNS)


def write_filter_results(rows: Sequence[dict[str, Any]], out: str | os.PathLike, header: dict[str, Any]) -> None:
    """``out`` with suffixes .csv, .json and .md, each written atomically."""
    write_results(out, header, rows, filter_table(rows))


#: header keys that describe one invocation's filters rather than its episodes; the rows carry the
#: same facts (kind, gamma, backup_horizon, backup_disturbance, policy), so tables that differ only in these merge
PER_INVOCATION_KEYS = ("filters", "gammas", "backup_horizon", "backup_disturbance", "policy")


def _episode_header(header: dict[str, Any]) -> dict[str, Any]:
    """The keys of a table's header that fix its episodes, as they read back from the JSON file."""
    kept = {k: v for k, v in header.items() if k not in PER_INVOCATION_KEYS and k != "results"}
    return json.loads(json.dumps(kept, default=str, sort_keys=True))


def filter_table_rows(out: str | os.PathLike, header: dict[str, Any]) -> list[dict[str, Any]]:
    """The rows of the filter table already at ``out`` that a study with ``header`` may merge into
    (none if there is no table). A table of other episodes (another scene, seed, count, start rule,
    pursuer, nominal policy, ...) raises ``ValueError`` naming the first setting that differs: its
    rows were not measured on the same episodes, so they cannot share a table. ``reach filter-eval``
    calls this before any episode runs, and again under the table's lock when it writes."""
    return _stored_filter_table(out, header).get("results", [])


def _stored_filter_table(out: str | os.PathLike, header: dict[str, Any]) -> dict[str, Any]:
    """The whole table at ``out`` (header and rows; ``{}`` if there is none), checked as
    :func:`filter_table_rows` says."""
    path = Path(out).with_suffix(".json")
    if not path.exists():
        return {}
    data = current_names(read_json(path, "existing filter results", hint="; move the file away to start over"))
    if not isinstance(data.get("results"), list):
        raise ValueError(f"{path} is not a filter results table; use another --out or delete it")
    data["results"] = restore_nan(data["results"])  # strict JSON wrote NaN as null
    old, new = _episode_header(data), _episode_header(header)
    for key in sorted(old.keys() | new.keys()):
        if old.get(key) != new.get(key):
            raise ValueError(
                f"{path} holds filter results for other episodes ({key}: {old.get(key)!r} there, "
                f"{new.get(key)!r} now); use another --out or delete it"
            )
    return data


def merge_filter_results(
    rows: Sequence[dict[str, Any]], out: str | os.PathLike, header: dict[str, Any]
) -> list[dict[str, Any]]:
    """Merge ``rows`` into the filter table at ``out`` and rewrite it; returns the merged rows.

    As ``reach evaluate`` does with its table: rows of configurations already there and not rerun
    are kept (a second ``reach filter-eval`` with another value function into the same ``--out``
    adds its rows instead of erasing the first's), a row with the same label replaces the old one,
    and the read-merge-write runs under a lock on ``out.lock``."""
    out = Path(out)
    with exclusive_lock(out.with_suffix(".lock"), f"filter results {out}", wait=True):
        stored = _stored_filter_table(out, header)  # one read: its rows and its header
        merged = merge_rows(stored.get("results", []), rows, key="label")
        joined = dict(header)
        for key in ("filters", "gammas"):  # the union of what the merged invocations ran
            lists = [v for v in (stored.get(key), header.get(key)) if isinstance(v, list)]
            if lists:
                joined[key] = list(dict.fromkeys(x for values in lists for x in values))
        write_filter_results(merged, out, joined)
    return merged


__all__ = [
    "FILTER_COLUMNS",
    "PER_INVOCATION_KEYS",
    "backup_horizon_of",
    "filter_table",
    "filter_table_rows",
    "labelled",
    "merge_filter_results",
    "settings_columns",
    "write_filter_results",
]
