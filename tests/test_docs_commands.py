"""Every `reach` command in the docs' shell blocks parses as written: options that were renamed or
removed, and number lists the command would refuse (`--times 0,0.1,...,1.0` once was), fail here
instead of in a reader's terminal. The commands are parsed, not run."""

from __future__ import annotations

import itertools
import re
import shlex
from pathlib import Path

import pytest

from reach.validation import csv_floats
from reach_cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "docs" / "results").glob("*.md"))]
#: options whose value is a list of numbers, checked as the commands check them
NUMBER_LISTS = ("--times", "--thresholds", "--gammas")


def shell_blocks(text: str) -> list[str]:
    """The bodies of the page's ```bash / ```sh / bare fenced blocks, continuation lines joined."""
    blocks, body, language = [], None, ""
    for line in text.splitlines():
        if line.strip().startswith("```"):
            if body is None:
                body, language = [], line.strip()[3:]
            else:
                if language in ("bash", "sh", ""):
                    blocks.append(re.sub(r"\\\n\s*", " ", "\n".join(body)))
                body = None
        elif body is not None:
            body.append(line)
    return blocks


def reach_commands() -> list[tuple[str, list[str]]]:
    found = []
    for page in PAGES:
        for block in shell_blocks(page.read_text()):
            for line in block.splitlines():
                m = re.search(r"(?:^|;\s*|&&\s*|\bdo\s+)(reach\s.*)$", line.strip())
                if not m:
                    continue
                argv = shlex.split(m.group(1), comments=True)[1:]
                if argv and not any(c in a for a in argv for c in "$<{"):  # shell variables, placeholders
                    found.append((f"{page.relative_to(ROOT)}: {m.group(1)[:80]}", argv))
    return found


COMMANDS = reach_commands()


def test_the_docs_hold_reach_commands():
    assert len(COMMANDS) >= 25, f"found only {len(COMMANDS)} commands: has the docs' layout changed?"


@pytest.mark.parametrize("argv", [argv for _, argv in COMMANDS], ids=[name for name, _ in COMMANDS])
def test_every_reach_command_in_the_docs_parses(argv):
    try:
        build_parser().parse_args(argv)
    except SystemExit as exit_:
        pytest.fail(f"reach {' '.join(argv)}: argparse refused it (exit {exit_.code})")
    for option, value in itertools.pairwise(argv):
        if option in NUMBER_LISTS:
            csv_floats(option, value)
