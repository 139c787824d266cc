"""The base layer and the solver and training packages import without Gymnasium or PettingZoo."""

from __future__ import annotations

import subprocess
import sys


def test_groundtruth_and_training_load_no_gymnasium():
    code = (
        "import sys, groundtruth, training, reach.systems\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('gymnasium', 'pettingzoo', 'reach_envs')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out
