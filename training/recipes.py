"""Named training recipes: settings measured to work together for one system and budget.

A recipe is a dict of :class:`~training.config.TrainConfig` fields beyond the defaults, so it
composes with any other setting (``TrainConfig(system="air3d", budget_s=180, **AIR3D_FAST)``) and
with the command line (``reach train --system air3d --budget 3m --points 2048``). Each one's numbers
come from a benchmark in ``benchmarks/`` and are in the docs.
"""

from __future__ import annotations

from typing import Any

__all__ = ["AIR3D_FAST"]

#: Air3D in three CPU minutes (issue 45): the defaults at a quarter of the points per step, so that
#: a 2-core CPU takes about 3.9x as many (smaller) steps in the same time, and reaches DeepReach's
#: published accuracy (volume IoU 0.957, MSE 1.8e-4 at t = 1.0) within a 3-minute budget on 3 runs
#: of 4: IoU 0.962-0.976 and MSE 0.9-1.4e-4 on 3 seeds, 0.953 and 2.2e-4 on the fourth, against
#: 0.918-0.958 and 2.3-6.4e-4 for the defaults
#: (``benchmarks/air3d_three_minutes.py``; docs/training.md). ``reach demo`` trains with it.
AIR3D_FAST: dict[str, Any] = {"points": 2048}
