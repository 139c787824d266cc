"""The house's floors: every module imports only its own floor or those below, and nothing loops.

Floors, bottom up (``docs/design.md`` draws them):

0. ``reach_runtime`` - the exported filter's runtime (NumPy and ONNX Runtime): imports none of ours;
1. ``reach`` - systems, value-function protocol, integrators, atomic writes, locks, validation;
2. ``reach_envs`` and ``groundtruth`` - environments and the grid solver, side by side (neither
   imports the other);
3. ``training`` - value networks, their training and checkpoints, the DeepReach import;
4. ``safety`` - the safety core: policies, filters, rollouts, verification, loaders, env adapters;
5. ``studies`` - batch evaluation, filter studies, sweeps, plots, tables, the demo;
6. ``reach_cli`` (and ``reach.__main__``, the ``python -m reach`` entry) - the command line.

Every ``import`` statement counts, function-local and ``TYPE_CHECKING`` ones included, and so does
``importlib.import_module("literal")``. No module names a higher floor, with no exception: nothing has
been released, so a moved path leaves no alias behind (the changelog says what moved).
"""

from __future__ import annotations

import ast
import io
import json
import re
import subprocess
import sys
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = (
    "reach_runtime", "reach", "reach_envs", "groundtruth", "training", "safety", "studies", "reach_cli"
)  # fmt: skip
FLOORS = {
    "reach_runtime": 0,
    "reach": 1,
    "reach_envs": 2,
    "groundtruth": 2,
    "training": 3,
    "safety": 4,
    "studies": 5,
    "reach_cli": 6,
    "reach.__main__": 6,
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            found[_module_name(path)] = path
    return found


MODULES = _modules()


def _floor(module: str) -> int:
    """The floor of a module: its longest prefix in :data:`FLOORS`."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        prefix = ".".join(parts[:n])
        if prefix in FLOORS:
            return FLOORS[prefix]
    raise AssertionError(f"{module} lies on no floor; add its package to FLOORS")


def _resolve(name: str) -> str | None:
    """The project module an import names (``a.b.c`` may be a module or a name in ``a.b``)."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def _imports(module: str) -> list[tuple[str, int, str]]:
    """``(imported module, line, source line)`` for every project import in ``module``."""
    path = MODULES[module]
    source = path.read_text()
    lines = source.splitlines()
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(source)):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base]) if base else ".".join(anchor)
            names = [f"{base}.{alias.name}" for alias in node.names]
        elif (
            isinstance(node, ast.Call)
            and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            names = [node.args[0].value]
        for name in names:
            target = _resolve(name)
            if target is not None and target != module:
                found.append((target, node.lineno, lines[node.lineno - 1]))
    return found


GRAPH = {module: _imports(module) for module in MODULES}


def test_every_module_lies_on_a_floor():
    assert MODULES, "no modules found"
    for module in MODULES:
        _floor(module)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_down_the_floors(module):
    floor = _floor(module)
    for target, line, _ in GRAPH[module]:
        assert _floor(target) <= floor, f"{module}:{line} (floor {floor}) imports {target} (floor {_floor(target)})"


def test_envs_and_grid_solver_do_not_import_each_other():
    for module in MODULES:
        if module.split(".")[0] in ("reach_envs", "groundtruth"):
            other = "groundtruth" if module.startswith("reach_envs") else "reach_envs"
            for target, line, _ in GRAPH[module]:
                assert target.split(".")[0] != other, f"{module}:{line} imports {target}"


def test_no_import_loops():
    """No module reaches itself through imports, however deep and wherever the import sits."""
    edges = {m: {t for t, _, _ in GRAPH[m]} for m in MODULES}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    loops: list[list[str]] = []
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in edges:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                loops.append(sorted(component))

    for v in edges:
        if v not in index:
            visit(v)
    assert not loops, f"import loops: {loops}"


def test_no_alias_or_deprecation_machinery_is_left():
    """Nothing has been released: a moved path leaves no alias module, no warning shim, no re-export."""
    for module, path in MODULES.items():
        source = path.read_text()
        assert "DeprecationWarning" not in source, f"{module} still warns of a deprecated name"
        assert "reach.deprecation" not in source, f"{module} imports the removed alias layer"


def test_groundtruth_and_training_load_no_gymnasium():
    code = (
        "import sys, groundtruth, training, reach.systems\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('gymnasium', 'pettingzoo', 'reach_envs')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


#: the comment that keeps a function-local import: ``# lazy: <why>`` on the import's first line, or
#: on its own line directly above a run of consecutive import statements (covering the whole run)
LAZY_MARK = re.compile(r"#\s*lazy:\s*\S")


def _comments(source: str) -> dict[int, tuple[str, bool]]:
    """``line -> (comment, alone on its line)`` for every comment in ``source``."""
    found = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            found[tok.start[0]] = (tok.string, not tok.line[: tok.start[1]].strip())
    return found


def _function_local_imports(tree: ast.AST) -> list[tuple[ast.stmt, list[ast.stmt]]]:
    """``(import statement, the statement list holding it)`` for every import inside a function body."""
    found = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for _, value in ast.iter_fields(node):
            children = value if isinstance(value, list) else [value]
            for child in children:
                if not isinstance(child, ast.AST):
                    continue
                if in_function and isinstance(child, (ast.Import, ast.ImportFrom)):
                    found.append((child, value))
                inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
                visit(child, inner)

    visit(tree, False)
    return found


def _unmarked_local_imports(path: Path) -> list[str]:
    source = path.read_text()
    comments = _comments(source)

    def marked(line: int, alone: bool) -> bool:
        text, on_own_line = comments.get(line, ("", False))
        return bool(LAZY_MARK.match(text)) and on_own_line == alone

    bad = []
    for node, body in _function_local_imports(ast.parse(source)):
        if marked(node.lineno, alone=False):
            continue
        first = body.index(node)  # back to the first statement of this run of consecutive imports
        while (
            first > 0
            and isinstance(body[first - 1], (ast.Import, ast.ImportFrom))
            and body[first - 1].end_lineno + 1 == body[first].lineno
        ):
            first -= 1
        if not marked(body[first].lineno - 1, alone=True):
            bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    return bad


def test_function_local_imports_are_marked():
    """An import inside a function is kept only where it saves start-up or an optional dependency,
    and then says so (``# lazy: <why>``); any other belongs with the module's top-level imports."""
    bad = [line for path in MODULES.values() for line in _unmarked_local_imports(path)]
    listing = "\n".join(bad)
    assert not bad, f"function-local imports without a '# lazy: <why>' marker (hoist them or say why):\n{listing}"


def test_start_up_stays_light():
    """Building the CLI's parser, which every ``reach`` command does first, loads none of the env,
    plotting, recording or optional stacks: each command imports its own when it runs."""
    heavy = {"gymnasium", "pettingzoo", "matplotlib", "PIL", "imageio", "ray", "tensorboard"}
    code = "import json, sys, reach_cli; reach_cli.build_parser(); print(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    loaded = {name.split(".")[0] for name in json.loads(out)}
    assert not loaded & heavy, f"building the parser loads {sorted(loaded & heavy)}"
