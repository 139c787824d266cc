"""`reach demo` end to end at toy size: every stage runs and the report links files that exist.

Marked ``slow`` (about 40 s, two thirds of it rendering the episode GIF twice) to keep the default
suite under 10 minutes on 2 cores; CI (``.ci/run``) runs it by name in its slow step."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from studies.demo import run_demo


@pytest.mark.slow
def test_demo_writes_a_report_and_resumes(tmp_path: Path):
    out = tmp_path / "demo"
    lines: list[str] = []
    kwargs = dict(budget_s=2.0, grid=21, samples=300, episodes=40, progress=False, compile=False)
    report = run_demo(out, log=lines.append, **kwargs)
    text = report.read_text()
    assert "| air3d_gt | grid |" in text and "| air3d-ssssl | ssssl |" in text
    assert "| nominal |" in text and "trained ssssl greedy @ 0.06" in text  # the switch, its default backup input
    for link in re.findall(r"\]\(([^)]+)\)", text):
        assert (out / link).stat().st_size > 1000, link
    assert [line[:5] for line in lines] == ["[1/5]", "[2/5]", "[3/5]", "[4/5]", "[5/5]"]
    # a second run reuses the ground truth, the finished training run and the verification rows
    lines.clear()
    run_demo(out, log=lines.append, **kwargs)
    assert [line[:5] for line in lines] == ["[3/5]", "[4/5]", "[5/5]"]
