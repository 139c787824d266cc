"""The README's Python tour runs as written (in a temporary directory), so the door never lies."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_api_tour_runs(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no Python tour"
    monkeypatch.chdir(tmp_path)
    for block in blocks:
        exec(compile(block, str(README), "exec"), {"__name__": "readme"})
    assert (tmp_path / "runs" / "demo" / "checkpoint.pt").exists()


def test_readme_stays_a_door():
    lines = README.read_text().splitlines()
    assert len(lines) <= 250, f"README has {len(lines)} lines; measured detail belongs in docs/"
    for link in re.findall(r"\]\((docs/[^)#]+)", README.read_text()):
        assert (README.parent / link).exists(), link


def test_readme_tables_are_well_formed():
    """Every row of a README table has its header's cells (a stray or missing `|` shifts a result
    into the wrong column, or drops its link to the details)."""
    header = None
    for number, line in enumerate(README.read_text().splitlines(), 1):
        if not line.startswith("|"):
            header = None
            continue
        cells = line.strip().strip("|").count("|") + 1
        if header is None:
            header = cells
        assert cells == header, f"README.md:{number} has {cells} cells, its table's header {header}"
