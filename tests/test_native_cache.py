"""The native engine's build cache fails closed: a cached library is loaded only where its size and
SHA-256 match the record its build wrote (reach_runtime.native.build). A truncated library used to
kill the process with SIGBUS when loaded; a truncated, garbage or foreign library, or one without a
valid record, is now rebuilt, and one that cannot be rebuilt is refused in one error naming it.

The graph is a one-node model (it builds in well under a second); loading a damaged cache runs in a
subprocess, so that a crash would fail the test rather than end the test run."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper  # noqa: E402

from reach_runtime.native import compile_filter  # noqa: E402
from reach_runtime.native.build import file_record, is_recorded  # noqa: E402

pytestmark = pytest.mark.skipif(
    not any(shutil.which(c) for c in ("cc", "gcc", "clang")), reason="the native engine needs a C compiler"
)

ROOT = Path(__file__).resolve().parents[1]

#: loads the library of the model argv[1] from the cache argv[2] and prints its output for one row
LOAD = """
import sys
import numpy as np
from reach_runtime.native import NativeGraph
graph = NativeGraph(sys.argv[1], cache=sys.argv[2])
print(repr(float(graph.run({"x": np.array([[0.5, -2.0]], np.float32)})[0][0, 1])))
"""


def _model(path: Path, op: str) -> Path:
    graph = helper.make_graph(
        [helper.make_node(op, ["x"], ["y"])],
        "one",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["b", 2])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["b", 2])],
    )
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)], ir_version=10), path)
    return path


@pytest.fixture
def built(tmp_path):
    """A model (``Neg``), its cache, its built library and the library's bytes."""
    model = _model(tmp_path / "neg.onnx", "Neg")
    cache = tmp_path / "cache"
    library = compile_filter(model, cache)  # builds without loading: this process never maps it
    return model, cache, library, library.read_bytes()


def _record(library: Path) -> dict:
    return json.loads(library.with_suffix(".json").read_text())


def test_a_build_records_its_library_and_a_recorded_library_is_reused(built):
    model, cache, library, data = built
    assert _record(library) == {"library": library.name, **file_record(library)}
    assert _record(library)["bytes"] == len(data) and is_recorded(library)
    inode = library.stat().st_ino
    assert compile_filter(model, cache) == library and library.stat().st_ino == inode  # not rebuilt


def _damage(library: Path, how: str, tmp_path: Path) -> None:
    data = library.read_bytes()
    if how == "truncated":
        library.write_bytes(data[: len(data) // 3])
    elif how == "garbage":
        library.write_bytes(np.random.default_rng(0).bytes(len(data)))  # the right size, not the right bytes
    elif how == "foreign":  # another valid library, of another graph
        library.write_bytes(compile_filter(_model(tmp_path / "abs.onnx", "Abs"), tmp_path / "other").read_bytes())
    elif how == "no record":  # an interrupted build, or a cache written before records
        library.with_suffix(".json").unlink()
    elif how == "bad record":
        library.with_suffix(".json").write_text("{not json")
    else:
        raise AssertionError(how)


@pytest.mark.parametrize("how", ["truncated", "garbage", "foreign", "no record", "bad record"])
def test_a_damaged_cached_library_is_rebuilt(built, tmp_path, how):
    model, cache, library, data = built
    _damage(library, how, tmp_path)
    assert not is_recorded(library)
    assert compile_filter(model, cache) == library
    assert library.read_bytes() == data and is_recorded(library)


@pytest.mark.parametrize("how", ["truncated", "garbage"])
def test_loading_a_damaged_cache_rebuilds_it_and_the_process_survives(built, tmp_path, how):
    """The load itself (ctypes), in a fresh process: before the records, a truncated library ended
    it with SIGBUS."""
    model, cache, library, data = built
    _damage(library, how, tmp_path)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    result = subprocess.run(
        [sys.executable, "-c", LOAD, str(model), str(cache)], capture_output=True, text=True, env=env, timeout=120
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert float(result.stdout.strip()) == 2.0  # Neg of -2
    assert library.read_bytes() == data and is_recorded(library)


def test_a_damaged_library_that_cannot_be_rebuilt_is_refused_naming_it(built):
    """Where the cache cannot take the rebuilt library (here a folder stands in its place), one
    ``ValueError`` names the file; nothing is loaded."""
    model, cache, library, _ = built
    library.unlink()
    library.mkdir()
    with pytest.raises(ValueError, match=rf"{library.name}: the cached library does not match its record.*rebuilt"):
        compile_filter(model, cache)
