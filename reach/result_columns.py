"""Result columns and settings renamed before the first release, read into their current names.

The statistical guarantee was once written with the words of the formal one ("certify",
"certified"); those words now mean a proof only (:mod:`safety.formal`). Files written before the
rename (results tables, model cards, sweep scores) still load: :func:`current_names` renames their
keys on the way in, so every reader sees one vocabulary.
"""

from __future__ import annotations

from typing import Any

#: a key written by an earlier version -> its name today
RENAMED: dict[str, str] = {
    "certify_samples": "scenario_samples",
    "certified_volume": "scenario_volume",
    "robust_certified_volume": "robust_scenario_volume",
    "certified_samples": "scenario_states",
    "certified_failures": "scenario_failures",
    "certify_reused": "scenario_reused",
    "certify_error": "scenario_error",
}


def current_names(data: Any) -> Any:
    """``data`` with every dictionary key of :data:`RENAMED`, at any depth, under its current name.

    A key whose current name is present too keeps the current one's value (a file cannot hold two)."""
    if isinstance(data, dict):
        out = {}
        for key, value in data.items():
            new = RENAMED.get(key, key) if isinstance(key, str) else key
            if new != key and new in data:
                continue
            out[new] = current_names(value)
        return out
    if isinstance(data, list):
        return [current_names(item) for item in data]
    return data


__all__ = ["RENAMED", "current_names"]
