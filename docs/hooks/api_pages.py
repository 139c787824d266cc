"""MkDocs hook: every public module of every package has a ``::: module`` block on its API page.

The API reference (``docs/api/PACKAGE.md``) lists its modules by hand, in reading order; this hook
warns (so ``mkdocs build --strict`` fails) when a package has a public module that its page does not
document, so that a new module cannot go missing from the reference. Public: no part of the dotted
name starts with ``_``, and it is not ``__main__``.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

log = logging.getLogger("mkdocs.hooks.api_pages")

PACKAGES = ("reach", "reach_envs", "groundtruth", "training", "safety", "studies", "reach_cli", "reach_runtime")
BLOCK = re.compile(r"^:::\s+([\w.]+)\s*$", re.M)


def public_modules(root: Path, package: str) -> list[str]:
    """The public modules of ``package`` (a folder under ``root``), the package itself included."""
    found = []
    base = root / package
    for path in sorted(base.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if any(part.startswith("_") for part in parts):
            continue
        if not all((root.joinpath(*parts[:i]) / "__init__.py").is_file() for i in range(1, len(parts))):
            continue  # a folder that is not a package (data, templates)
        found.append(".".join(parts))
    return found


def on_files(files: Any, config: Any) -> Any:
    root = Path(config["config_file_path"]).parent
    docs = Path(config["docs_dir"])
    for package in PACKAGES:
        if not (root / package / "__init__.py").is_file():
            continue
        page = docs / "api" / f"{package}.md"
        if not page.is_file():
            log.warning("api_pages: package %s has no API page (docs/api/%s.md)", package, package)
            continue
        documented = set(BLOCK.findall(page.read_text(encoding="utf-8")))
        for module in public_modules(root, package):
            if module not in documented:
                log.warning("api_pages: docs/api/%s.md does not document %s (add '::: %s')", package, module, module)
    return files
