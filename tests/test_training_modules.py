"""The split modules keep their old import paths, and neither package has an import loop, even local."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at top level or inside functions (``TYPE_CHECKING`` blocks too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
    return found


def _graph(package: str) -> dict[str, set[str]]:
    """Imports among a package's own modules (its ``__init__`` aside: it imports them all)."""
    files = {f"{package}.{p.stem}": p for p in (ROOT / package.replace(".", "/")).glob("*.py") if p.stem != "__init__"}
    return {name: _imports(path) & set(files) for name, path in files.items()}


@pytest.mark.parametrize("package", ["reach.systems", "training"])
def test_no_module_imports_itself_back(package):
    graph = _graph(package)

    def visit(name: str, path: tuple[str, ...]) -> None:
        for dep in graph[name]:
            assert dep not in path, f"import loop: {' -> '.join((*path, dep))}"
            visit(dep, (*path, dep))

    for name in graph:
        visit(name, (name,))


def test_only_the_package_imports_the_registry():
    importers = [n for n, deps in _graph("reach.systems").items() if "reach.systems.registry" in deps]
    assert importers == []


def test_moved_names_import_from_where_they_were():
    import reach.systems
    import reach.systems.box
    import reach.systems.class_names
    import reach.systems.deepreach_normalisation
    import training
    import training.run_directory
    import training.sampling
    import training.signals
    from reach.systems.base import NO_INPUT, Box, DeepReachNormalisation
    from reach.systems.registry import SYSTEMS, import_path, system_reference
    from training.trainer import (
        RESUME_OVERRIDABLE,
        Trainer,
        _clean_metrics,
        _deferred_signals,
        build_network,
        moved_run_seed,
    )

    assert Box is reach.systems.Box is reach.systems.box.Box and Box((), ()) == NO_INPUT
    assert DeepReachNormalisation is reach.systems.DeepReachNormalisation
    assert DeepReachNormalisation is reach.systems.deepreach_normalisation.DeepReachNormalisation
    assert system_reference is reach.systems.class_names.system_reference
    assert import_path(Box) == "reach.systems.box:Box" and system_reference(SYSTEMS["air3d"]) == "air3d"
    assert Trainer is training.Trainer and callable(build_network) and "steps" in RESUME_OVERRIDABLE
    assert moved_run_seed is training.sampling.moved_run_seed
    assert _clean_metrics is training.run_directory.clean_metrics
    assert _deferred_signals is training.signals.deferred_signals
