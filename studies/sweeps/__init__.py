"""Layout sweeps: layouts x seeds on a training budget, scored against a reference, with a report.

Part of the studies layer: it builds on training and the safety core, and only the CLI sits above.
"""

from studies.sweeps.report import claims, pareto_front, plot_pareto, summary_table
from studies.sweeps.spec import AIR3D_LAYOUTS, NINE_D_LAYOUTS, SweepSpec, load_spec
from studies.sweeps.sweep import run_sweep, write_report
from studies.sweeps.task import run_task

__all__ = [
    "AIR3D_LAYOUTS",
    "NINE_D_LAYOUTS",
    "SweepSpec",
    "claims",
    "load_spec",
    "pareto_front",
    "plot_pareto",
    "run_sweep",
    "run_task",
    "summary_table",
    "write_report",
]
