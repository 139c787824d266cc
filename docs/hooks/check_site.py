"""Check a built site for what a strict MkDocs build lets through but a reader sees as broken.

Usage: ``python docs/hooks/check_site.py SITE_DIR`` (after ``mkdocs build --site-dir SITE_DIR``).

Prints one line per problem, naming the page, and exits 1 if there is any:

* a raw pipe table: a paragraph whose text starts with ``|`` and holds a ``|---|`` separator row,
  i.e. a Markdown table that did not parse (most often an unescaped ``|`` inside a cell, which
  gives the header more cells than the separator);
* a raw list item: a paragraph line, after its first, that starts with ``- `` or ``1. ``, i.e. a
  Markdown list that did not parse (Python-Markdown needs a blank line before a list, and nested
  blocks in a list item indented by 4 spaces);
* an unresolved reST role (``:class:``, ``:func:``, ``:meth:``, ``:mod:``, ``:attr:``,
  ``:data:``, ``:exc:``, ``:obj:``) left in a page's text, i.e. a docstring role that the griffe
  extension (docs/hooks/griffe_roles.py) did not turn into a cross-reference.

Text inside ``<code>``, ``<pre>``, ``<script>`` and ``<style>`` is not checked: a page may show
a role or a table as an example.
"""

from __future__ import annotations

import re
import sys
from html.parser import HTMLParser
from pathlib import Path

ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|attr|data|exc|obj):")
PIPE_SEPARATOR = re.compile(r"\|\s*:?-{3,}:?\s*\|")
LIST_ITEM = re.compile(r"\s*(?:[-*+]|\d+[.)])\s+\S")
SKIPPED = {"code", "pre", "script", "style", "kbd", "samp"}
VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}


class _PageScanner(HTMLParser):
    """Collects each paragraph's text and the page's visible text (outside code, scripts and styles)."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.skip_depth = 0
        self.paragraph: list[str] | None = None
        self.paragraphs: list[str] = []
        self.text: list[tuple[str, bool]] = []  # (text, outside code) in page order

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        if tag in VOID:
            return
        if tag in SKIPPED:
            self.skip_depth += 1
        elif tag == "p" and self.skip_depth == 0:
            self._close_paragraph()
            self.paragraph = []

    def handle_startendtag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        pass

    def handle_endtag(self, tag: str) -> None:
        if tag in SKIPPED:
            self.skip_depth = max(0, self.skip_depth - 1)
        elif tag == "p":
            self._close_paragraph()

    def handle_data(self, data: str) -> None:
        if self.paragraph is not None:
            # code inside a paragraph still counts for the table test: a broken table's cells keep their code
            self.paragraph.append(data)
        self.text.append((data, self.skip_depth == 0))

    def _close_paragraph(self) -> None:
        if self.paragraph is not None:
            self.paragraphs.append("".join(self.paragraph))
            self.paragraph = None

    def close(self) -> None:
        super().close()
        self._close_paragraph()


def _shorten(text: str, width: int = 90) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 3] + "..."


def check_page(html: str) -> list[str]:
    """The problems on one built page, as messages without the page's name."""
    scanner = _PageScanner()
    scanner.feed(html)
    scanner.close()
    problems = []
    for paragraph in scanner.paragraphs:
        stripped = paragraph.strip()
        if stripped.startswith("|") and PIPE_SEPARATOR.search(stripped):
            problems.append(f"raw pipe table (a Markdown table that did not parse): {_shorten(stripped)!r}")
        for line in stripped.split("\n")[1:]:
            if LIST_ITEM.match(line):
                problems.append(f"raw list item (a Markdown list that did not parse): {_shorten(line)!r}")
    # roles are searched in the text outside code; the context shown includes the code around them
    text = "".join(chunk for chunk, _ in scanner.text)
    visible = "".join(chunk if outside else "\0" * len(chunk) for chunk, outside in scanner.text)
    for match in ROLE.finditer(visible):
        context = text[max(0, match.start() - 30) : match.end() + 50]
        problems.append(f"unresolved reST role {match.group(0)!r}: {_shorten(context)!r}")
    return problems


def check_site(site: Path) -> list[str]:
    """Every problem on every HTML page under ``site``, one line each, naming the page."""
    lines = []
    for page in sorted(site.rglob("*.html")):
        for problem in check_page(page.read_text(encoding="utf-8", errors="replace")):
            lines.append(f"{page.relative_to(site).as_posix()}: {problem}")
    return lines


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: check_site.py SITE_DIR", file=sys.stderr)
        return 2
    site = Path(argv[0])
    if not site.is_dir() or not any(site.rglob("*.html")):
        print(f"{site}: no built HTML pages (run mkdocs build --site-dir {site} first)", file=sys.stderr)
        return 2
    problems = check_site(site)
    for line in problems:
        print(line)
    pages = sum(1 for _ in site.rglob("*.html"))
    print(f"check_site: {len(problems)} problem(s) in {pages} pages", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
