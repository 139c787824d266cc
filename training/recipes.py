"""Named training recipes: settings measured to work together for one system and budget.

A recipe is a dict of :class:`~training.config.TrainConfig` fields beyond the defaults, so it
composes with any other setting (``TrainConfig(system="air3d", budget_s=180, **CPU_3D)``) and
with the command line (``reach train --system air3d --budget 3m --points 2048``). Each one was chosen
by a benchmark in ``benchmarks/``, whose results are on docs/results/training.md.
"""

from __future__ import annotations

from typing import Any

__all__ = ["CPU_3D"]

#: 3D systems on a CPU budget of minutes: the defaults at a quarter of the points per step, so that a CPU takes
#: 3.5-5x as many (smaller) steps in the same time and each still sees the whole curriculum. Measured on Air3D in
#: three minutes (issue 45, ``benchmarks/air3d_three_minutes.py``), and in ten on Dubins3D, the built-in
#: reach-avoid car and one written as a user would (issue 63, ``benchmarks/user_car_ten_minutes.py``); results on
#: docs/results/training.md, *Air3D in three minutes* and *A reach-avoid car of one's own in ten minutes*.
#: ``reach demo`` trains with it. The defaults keep 8,192 points, with which every card past three dimensions and
#: every GPU recipe was measured.
CPU_3D: dict[str, Any] = {"points": 2048}
