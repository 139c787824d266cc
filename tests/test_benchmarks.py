"""The benchmark entry point runs its scripts (smoke size) and compares with an earlier run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_run_all_quick_and_compare(tmp_path: Path):
    cmd = [sys.executable, str(ROOT / "benchmarks" / "run_all.py"), "--quick", "--only", "rollouts"]
    first = subprocess.run([*cmd, "--out", str(tmp_path / "a")], capture_output=True, text=True, cwd=ROOT)
    assert first.returncode == 0, first.stderr
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["runs"][0]["exit"] == 0 and "agrees with reach" in summary["runs"][0]["tables"]
    second = subprocess.run(
        [*cmd, "--out", str(tmp_path / "b"), "--compare", str(tmp_path / "a" / "summary.json")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert second.returncode == 0, second.stderr
    assert "| previous wall (s) | ratio |" in second.stdout
    assert "## rollouts:" in (tmp_path / "b" / "report.md").read_text()
