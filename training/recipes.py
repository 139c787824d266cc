"""Named training recipes: settings measured to work together for one system and budget.

A recipe is a dict of :class:`~training.config.TrainConfig` fields beyond the defaults, so it
composes with any other setting (``TrainConfig(system="air3d", budget_s=180, **AIR3D_FAST)``) and
with the command line (``reach train --system air3d --budget 3m --points 2048``). Each one was chosen
by a benchmark in ``benchmarks/``, whose results are on docs/results/training.md.
"""

from __future__ import annotations

from typing import Any

__all__ = ["AIR3D_FAST"]

#: Air3D in three CPU minutes (issue 45): the defaults at a quarter of the points per step, so that a CPU takes
#: several times as many (smaller) steps in the same time and each still sees the whole curriculum,
#: for DeepReach's published accuracy within a 3-minute budget (``benchmarks/air3d_three_minutes.py``;
#: measured: docs/results/training.md, *Air3D in three minutes*). ``reach demo`` trains with it.
AIR3D_FAST: dict[str, Any] = {"points": 2048}
