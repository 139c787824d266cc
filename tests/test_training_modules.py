"""Moved names live in their real homes (no alias layer), and neither package has an import loop, even local."""

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


def test_moved_names_live_in_their_real_homes():
    import reach.systems
    import reach.systems.base
    import reach.systems.class_names
    import training
    import training.trainer
    from reach.systems.box import NO_INPUT, Box
    from reach.systems.deepreach_normalisation import DeepReachNormalisation
    from reach.systems.registry import SYSTEMS, import_path, system_reference
    from training.run_directory import RESUME_OVERRIDABLE, clean_metrics
    from training.sampling import moved_run_seed
    from training.signals import deferred_signals
    from training.trainer import Trainer, build_network

    assert Box is reach.systems.Box and Box((), ()) == NO_INPUT
    assert DeepReachNormalisation is reach.systems.DeepReachNormalisation
    assert system_reference is reach.systems.class_names.system_reference
    assert import_path(Box) == "reach.systems.box:Box" and system_reference(SYSTEMS["air3d"]) == "air3d"
    assert import_path(DeepReachNormalisation) == "reach.systems.deepreach_normalisation:DeepReachNormalisation"
    assert Trainer is training.Trainer and callable(build_network) and "steps" in RESUME_OVERRIDABLE
    assert moved_run_seed.__module__ == "training.sampling"
    assert clean_metrics.__module__ == "training.run_directory"
    assert deferred_signals.__module__ == "training.signals"
    # no alias layer: the trainer neither re-exports nor renames its helpers
    for name in ("_clean_metrics", "_deferred_signals", "_upper_bound", "moved_run_seed", "RESUME_OVERRIDABLE"):
        assert not hasattr(training.trainer, name), name
    assert set(training.trainer.__all__) == {"Trainer", "TrainingDivergedError", "TrainingInterrupted", "build_network"}
    assert not hasattr(Trainer, "residual_fn") and not hasattr(Trainer, "snapshot_dir")


#: names that moved out of a module, and the module each now lives in
_MOVED = {
    ("reach.systems.base", "Box"): "reach.systems.box",
    ("reach.systems.base", "NO_INPUT"): "reach.systems.box",
    ("reach.systems.base", "DeepReachNormalisation"): "reach.systems.deepreach_normalisation",
    **{
        ("training.trainer", name): home
        for name, home in {
            "LEGACY_DEFAULTS": "training.run_directory",
            "RESUME_OVERRIDABLE": "training.run_directory",
            "RUN_FILES": "training.run_directory",
            "Evaluator": "training.progress",
            "moved_run_seed": "training.sampling",
        }.items()
    },
}


_SOURCES = ("reach", "reach_envs", "groundtruth", "training", "safety", "studies", "reach_cli", "reach_runtime")
_SOURCES += ("tests", "benchmarks", "examples")


def test_nothing_imports_a_moved_name_from_its_old_module():
    """Every caller (library, tests, benchmarks, examples) imports a moved name from its real home."""
    found = []
    for folder in _SOURCES:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                    for alias in node.names:
                        if (node.module, alias.name) in _MOVED:
                            home = _MOVED[node.module, alias.name]
                            found.append(f"{path.relative_to(ROOT)}: {alias.name} from {node.module}, not {home}")
    assert found == []
