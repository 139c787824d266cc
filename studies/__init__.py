"""Studies: experiments built from the layers below, which nothing in the library depends on.

The top floor under the command line. Each module runs or reports an experiment:

* :mod:`studies.batch_verification` - :func:`evaluate_many`, the verification of many checkpoints
  on the same states, as a resumable table (``reach evaluate``);
* :mod:`studies.filter_study` - what a safety filter changes in episodes of a task
  (``reach filter-eval``), with :mod:`studies.goal_tasks` (the nominal task controllers);
* :mod:`studies.sweeps` - layouts x seeds on a training budget, with a report (``reach sweep``);
* :mod:`studies.step_budget_study`, :mod:`studies.step_budget_report` - named 9D recipes trained
  at fixed step budgets and seeds, scored into one table, reported (``benchmarks/nine_d_*.py``);
* :mod:`studies.plots`, :mod:`studies.tables` - BRT slices, bars, trade-offs and GIFs; Markdown
  tables and results files;
* :mod:`studies.demo` - Air3D end to end (``reach demo``).

Names are imported on first use, so that ``import studies.tables`` stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from reach.lazy import lazy_exports

if TYPE_CHECKING:
    from studies.batch_verification import References, evaluate_many, load_results, markdown_table
    from studies.filter_study import FilterStudy, run_filter_study

_LAZY = {
    "evaluate_many": "studies.batch_verification",
    "load_results": "studies.batch_verification",
    "markdown_table": "studies.batch_verification",
    "FilterStudy": "studies.filter_study",
    "run_filter_study": "studies.filter_study",
    "References": "studies.batch_verification",
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = ["FilterStudy", "References", "evaluate_many", "load_results", "markdown_table", "run_filter_study"]
