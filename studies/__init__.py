"""Studies: experiments built from the layers below, which nothing in the library depends on.

The top floor under the command line. Each module runs or reports an experiment:

* :mod:`studies.batch_verification` - :func:`evaluate_many`, the verification of many checkpoints
  on the same states, as a resumable table (``reach evaluate``);
* :mod:`studies.filter_eval` - what a safety filter changes in episodes of a task
  (``reach filter-eval``), with :mod:`studies.tasks` (the nominal task controllers);
* :mod:`studies.sweeps` - layouts x seeds on a training budget, with a report (``reach sweep``);
* :mod:`studies.plots`, :mod:`studies.tables` - BRT slices, bars, trade-offs and GIFs; Markdown
  tables and results files;
* :mod:`studies.demo` - Air3D end to end (``reach demo``).

Names are imported on first use, so that ``import studies.tables`` stays light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from studies.batch_verification import evaluate_many, load_results, markdown_table
    from studies.filter_eval import FilterStudy, run_filter_study

_LAZY = {
    "evaluate_many": "studies.batch_verification",
    "load_results": "studies.batch_verification",
    "markdown_table": "studies.batch_verification",
    "FilterStudy": "studies.filter_eval",
    "run_filter_study": "studies.filter_eval",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'studies' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__all__ = ["FilterStudy", "evaluate_many", "load_results", "markdown_table", "run_filter_study"]
