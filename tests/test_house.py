"""The house limits on the library's size, read from its source with ``ast`` (nothing is imported):

* no module over :data:`MAX_MODULE_LINES` lines;
* no class over :data:`MAX_CLASS_LINES` lines, unless its docstring says why, in a sentence that
  holds the words "over 300 lines" and a reason;
* no function or method with more than :data:`MAX_NAMED_PARAMETERS` named parameters (``self`` and
  ``cls`` not counted, nor ``*args`` and ``**kwargs``): options that travel together go into a
  frozen settings object instead.

Each test names every file, class or function over its limit, so one run shows all that is left.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: the library's packages, bottom floor first (tests/test_layers.py holds their order)
PACKAGES = ("reach_runtime", "reach", "reach_envs", "groundtruth", "training", "safety", "studies", "reach_cli")
MAX_MODULE_LINES = 500
MAX_CLASS_LINES = 300
MAX_NAMED_PARAMETERS = 8
#: the words a longer class's docstring must hold, with a reason in the same sentence
EXCUSE = "over 300 lines"
#: how many words that sentence needs besides the excuse itself to count as a reason
REASON_WORDS = 5


def _modules() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def _name(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _trees() -> list[tuple[Path, str, ast.Module]]:
    out = []
    for path in _modules():
        source = path.read_text()
        out.append((path, source, ast.parse(source, filename=str(path))))
    return out


TREES = _trees()


def named_parameters(node: ast.FunctionDef | ast.AsyncFunctionDef) -> list[str]:
    """The parameters a caller can name: positional-only, ordinary and keyword-only ones, without
    ``self`` and ``cls`` (``*args`` and ``**kwargs`` are not among them)."""
    a = node.args
    return [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs) if x.arg not in ("self", "cls")]


def excused(node: ast.ClassDef) -> bool:
    """Whether a class's docstring says why it is longer than the limit: a sentence with the words
    "over 300 lines" and at least :data:`REASON_WORDS` more words."""
    doc = ast.get_docstring(node) or ""
    for sentence in re.split(r"(?<=[.;:])\s+", " ".join(doc.split())):
        if EXCUSE in sentence and len(sentence.split()) - len(EXCUSE.split()) >= REASON_WORDS:
            return True
    return False


def test_the_walk_sees_every_package():
    """A package moved or renamed must not drop out of the checks unnoticed."""
    seen = {path.relative_to(ROOT).parts[0] for path, _, _ in TREES}
    assert seen == set(PACKAGES)
    assert len(TREES) > 100


def test_no_module_is_over_500_lines():
    long = [f"{_name(p)}: {n} lines" for p, source, _ in TREES if (n := len(source.splitlines())) > MAX_MODULE_LINES]
    assert not long, f"modules over {MAX_MODULE_LINES} lines (cut them by job):\n" + "\n".join(long)


def test_no_class_is_over_300_lines_unless_its_docstring_says_why():
    long = []
    for path, _, tree in TREES:
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_CLASS_LINES and not excused(node):
                    long.append(f"{_name(path)}: class {node.name}, {lines} lines")
    assert not long, (
        f"classes over {MAX_CLASS_LINES} lines whose docstring does not say why (move a job into a "
        f"collaborator, or say '{EXCUSE}' and why):\n" + "\n".join(long)
    )


def test_no_function_takes_more_than_8_named_parameters():
    wide = []
    for path, _, tree in TREES:
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                names = named_parameters(node)
                if len(names) > MAX_NAMED_PARAMETERS:
                    wide.append(f"{_name(path)}:{node.lineno}: {node.name} ({len(names)}: {', '.join(names)})")
    assert not wide, (
        f"functions with more than {MAX_NAMED_PARAMETERS} named parameters (group the options that travel "
        "together into a frozen settings object):\n" + "\n".join(wide)
    )


def _function(source: str) -> ast.FunctionDef:
    return ast.parse(source).body[0]


def _class(source: str) -> ast.ClassDef:
    return ast.parse(source).body[0]


@pytest.mark.parametrize(
    ("source", "count"),
    [
        ("def f(a, b, /, c, *args, d, e=1, **kwargs): pass", 5),
        ("def f(self, a, *, b): pass", 2),
        ("def f(cls, *args, **kwargs): pass", 0),
        ("async def f(a, b, c, d, e, f, g, h, i): pass", 9),
    ],
)
def test_named_parameters_count_what_a_caller_can_name(source, count):
    assert len(named_parameters(_function(source))) == count


@pytest.mark.parametrize(
    ("doc", "ok"),
    [
        ("A big class. It is over 300 lines because its states form one machine that must not be split.", True),
        ("A big class; over 300 lines.", False),  # the words alone are no reason
        ("A big class that does many things.", False),
        ("", False),
    ],
)
def test_a_long_class_needs_the_words_and_a_reason(doc, ok):
    assert excused(_class(f"class C:\n    {doc!r}\n")) is ok
