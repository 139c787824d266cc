"""The Python examples of the docs' user pages run as written, as the README's tour does
(tests/test_readme.py): every ```python block of each page below, in order, in one namespace per
page, in a temporary directory. A block that must not run here (hours of training) says so in its
fence, ```python title="not run", or with the comment `# docs: not run` in its body; keep those rare.

The how-to pages open with their example and its command line and keep their measurements in a
"Results" section; and no user page carries the project's working notes (issue numbers, commit
hashes, machine paths, test counts), which belong in the changelog."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from reach.threads import thread_policy

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: pages whose Python blocks run here
PAGES = ["index.md", "getting-started.md", "training.md", "verification.md", "filters.md", "studies.md"]
#: pages that open with a Python example and the equivalent command, measurements under "Results"
HOW_TO = ["training.md", "verification.md", "filters.md", "studies.md"]
NOT_RUN = "# docs: not run"

FENCE = re.compile(r"^(?P<indent>[ \t]*)```(?P<info>[^\n]*)\n(?P<body>.*?)^(?P=indent)```[ \t]*$", re.S | re.M)


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language and attributes, body with the fence's indentation removed) of every fenced block."""
    blocks = []
    for m in FENCE.finditer(text):
        indent = len(m["indent"])
        body = "\n".join(line[indent:] for line in m["body"].splitlines())
        blocks.append((m["info"].strip(), body + "\n"))
    return blocks


def runnable(info: str, body: str) -> bool:
    return info.split()[0:1] == ["python"] and 'title="not run"' not in info and NOT_RUN not in body


@pytest.mark.parametrize("page", PAGES)
def test_python_examples_run(page, tmp_path, monkeypatch):
    blocks = [body for info, body in fenced_blocks((DOCS / page).read_text()) if runnable(info, body)]
    assert blocks, f"docs/{page} has no runnable Python example"
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "docs_example"}
    with thread_policy():  # the cores other processes leave free, as `reach` and `verify` choose
        for number, block in enumerate(blocks, 1):
            exec(compile(block, f"docs/{page} (Python block {number})", "exec"), namespace)


@pytest.mark.parametrize("page", HOW_TO)
def test_how_to_pages_open_with_an_example(page):
    text = (DOCS / page).read_text()
    (first, example), (second, command) = fenced_blocks(text)[:2]
    assert runnable(first, example), f"docs/{page}: its first block ({first!r}) is no runnable Python example"
    assert second == "bash" and "reach " in command, f"docs/{page}: the example's command line should follow it"
    before_results = text.split("\n## Results", 1)
    assert len(before_results) == 2, f"docs/{page} has no '## Results' section"
    assert "|---" not in before_results[0], f"docs/{page}: a measured table stands above '## Results'"


def test_fence_parsing():
    text = 'x\n```python\na = 1\n```\n- item\n\n    ```python title="not run"\n    b = 2\n    ```\n'
    assert fenced_blocks(text) == [("python", "a = 1\n"), ('python title="not run"', "b = 2\n")]
    assert [runnable(*b) for b in fenced_blocks(text)] == [True, False]


# ---------------------------------------------------------------------- no working notes
USER_PAGES = sorted(p for p in DOCS.glob("*.md") if p.name != "changelog.md")  # docs/studies/ reports are generated
NOTES = {
    "an issue number": re.compile(r"\bissues? #?\d+", re.I),
    "a commit hash": re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b"),
    "a machine path": re.compile(r"/work/|\.\./shared\b"),
    "a test count": re.compile(r"\b\d[\d,]* tests\b"),
    "a note to ourselves": re.compile(r"HEAD at filing", re.I),
}


def working_notes(text: str) -> list[str]:
    return [f"{what}: {m.group(0)!r}" for what, pattern in NOTES.items() for m in pattern.finditer(text)]


@pytest.mark.parametrize("page", [*USER_PAGES, ROOT / "README.md"], ids=lambda p: p.name)
def test_user_pages_hold_no_working_notes(page):
    found = working_notes(page.read_text())
    assert not found, f"{page.name}: {found} (history belongs in docs/changelog.md)"


def card_text(value):
    """The text fields of a model card (not its digests, commits and numbers)."""
    if isinstance(value, dict):
        return [t for k, v in value.items() if k not in ("sha256", "commit") for t in card_text(v)]
    if isinstance(value, list):
        return [t for v in value for t in card_text(v)]
    return [value] if isinstance(value, str) else []


@pytest.mark.parametrize("card", sorted((ROOT / "training" / "pretrained").glob("*.card.json")), ids=lambda p: p.name)
def test_model_cards_hold_no_working_notes(card):
    found = [n for text in card_text(json.loads(card.read_text())) for n in working_notes(text)]
    assert not found, f"{card.name}: {found}"


def test_the_notes_are_recognised():
    assert len(working_notes("issue 18's goal; commit 20ce027; ../shared/reference; 543 tests")) == 4
    assert not working_notes("4x512, 1.84e-03, 92,400 steps, eps 2.81e-04, ssrsl, 101^3, 0.0025")
