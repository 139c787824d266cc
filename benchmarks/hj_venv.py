"""The interpreter the hj_reachability comparisons run: a virtual environment of their own.

hj_reachability (and JAX) is never a dependency of reach: ``benchmarks/hj_comparison.py`` and
``benchmarks/hj_kinds.py`` install it on first use into ``~/.cache/reach-bench/hj-venv``, unless
given an interpreter that already has it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HJ_VENV = Path.home() / ".cache" / "reach-bench" / "hj-venv"
HJ_REQUIREMENTS = ("hj_reachability==0.7.0", "jax[cpu]")


def hj_python(given: str | None) -> str:
    """An interpreter with hj_reachability: ``given``, or this benchmark's own virtual environment."""
    if given:
        return given
    python = HJ_VENV / "bin" / "python"
    if not python.exists():
        print(f"# installing {', '.join(HJ_REQUIREMENTS)} into {HJ_VENV} (for this benchmark only)", flush=True)
        subprocess.run([sys.executable, "-m", "venv", str(HJ_VENV)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "-q", *HJ_REQUIREMENTS], check=True)
    return str(python)
