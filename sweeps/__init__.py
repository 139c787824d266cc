"""Sweeps on top of training and safety: layout sweeps of accuracy against training time.

Data flows one way: systems -> envs / ground truth -> training -> safety -> sweeps.
"""

from sweeps.report import claims, pareto_front, plot_pareto, summary_table
from sweeps.spec import AIR3D_LAYOUTS, NINE_D_LAYOUTS, SweepSpec, load_spec
from sweeps.sweep import run_sweep, write_report
from sweeps.task import run_task

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
