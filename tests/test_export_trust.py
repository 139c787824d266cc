"""An exported filter is trusted as a checkpoint is: its digest covers its graph, weights and
metadata, and an edited, unsealed or foreign file is refused by both engines; the metadata the
graph bakes in (domain, threshold, problem kind, widths, a free batch) is checked against the graph
at load; a bad call (widths, overflowing or non-finite times, an empty batch) is one clear line;
and the file records, and ``reach export`` prints, whether its source passed the trust bar."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")
from onnx import numpy_helper  # noqa: E402

from reach_runtime import Filter  # noqa: E402
from reach_runtime.digest import DIGEST_KEY, ModelBytes, seal  # noqa: E402
from reach_runtime.native import c_source  # noqa: E402
from safety.filters.export import example_batch, source_verdict  # noqa: E402

ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Air3D's switch, exported once with ``reach export`` (its output read by the tests below)."""
    out = tmp_path_factory.mktemp("trust") / "air3d.onnx"
    command = ["export", "pretrained:air3d", "--out", str(out), "--dt", "0.05", "--check-states", "64"]
    done = subprocess.run(
        [sys.executable, "-m", "reach", *command],
        capture_output=True,
        text=True,
        env=ENV,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return out, done.stdout


def _edited(source: Path, target: Path, edit, reseal: bool = False) -> Path:
    """A copy of ``source`` with ``edit(model)`` applied, saved as onnx saves it (sealed again if asked)."""
    model = onnx.load(source)
    edit(model)
    data = model.SerializeToString()
    target.write_bytes(seal(data, str(target)) if reseal else data)
    return target


def _set_metadata(key: str, value):
    def edit(model):
        for prop in model.metadata_props:
            if prop.key == key:
                prop.value = json.dumps(value)
                return
        raise AssertionError(key)

    return edit


def _one_weight(model) -> None:
    """One element of one weight matrix nudged: the network, and so its decisions, change."""
    for tensor in model.graph.initializer:
        array = numpy_helper.to_array(tensor)
        if array.ndim == 2 and array.dtype == np.float32:
            array = array.copy()
            array[0, 0] += 0.5
            tensor.CopyFrom(numpy_helper.from_array(array, tensor.name))
            return
    raise AssertionError("no weight matrix")


def _drop_digest(model) -> None:
    kept = [p for p in model.metadata_props if p.key != DIGEST_KEY]
    assert len(kept) == len(model.metadata_props) - 1
    del model.metadata_props[:]
    model.metadata_props.extend(kept)


def test_the_exported_file_carries_a_digest_that_a_reserialization_keeps(exported, tmp_path):
    path, _ = exported
    model = ModelBytes(path.read_bytes(), str(path))
    assert json.loads(model.stored) == model.verify() and model.verify().startswith("sha256:")
    copy = _edited(path, tmp_path / "same.onnx", lambda m: None)  # onnx's load and save: the same bytes
    assert Filter.load(copy).metadata.fingerprint == Filter.load(path).metadata.fingerprint


@pytest.mark.parametrize(
    "name, edit",
    [
        ("weight", _one_weight),
        ("time_range", _set_metadata("reach.time_range", [0.0, 50.0])),
        ("no_digest", _drop_digest),
    ],
)
def test_an_edited_or_unsealed_file_is_refused_by_both_engines(exported, tmp_path, name, edit):
    """An edited weight would decide differently, an edited time range would decide at t = 50 s for
    a network that covers 1.1 s: each is refused, naming the file, by the ONNX Runtime engine and
    by the native engine's loader (before any C is written)."""
    bad = _edited(exported[0], tmp_path / f"{name}.onnx", edit)
    message = "carries no digest" if name == "no_digest" else "digest .* does not match its contents"
    with pytest.raises(ValueError, match=message) as caught:
        Filter.load(bad)
    assert str(bad) in str(caught.value) and len(str(caught.value).splitlines()) == 1
    with pytest.raises(ValueError, match=message):
        c_source(bad)
    with pytest.raises(ValueError, match=message):
        Filter.load(bad, engine="native")


#: metadata edits a sealed file could carry (its digest recomputed): key, new value from the old
#: metadata, and the refusal
SEALED_EDITS = {
    "threshold": (
        "reach.settings",
        lambda m: {**m.settings, "threshold": 0.6},
        "not decide by its metadata's threshold",
    ),
    "problem": ("reach.problem", lambda m: "reach", "on the side of a reach problem"),
    "domain": ("reach.domain", lambda m: [[-2.0, 2.0], *m.domain[1:]], "domain is not its metadata's"),
    "width": ("reach.state_dim", lambda m: 4, "the graph's state has width 3, its metadata says 4"),
    "default_time": ("reach.default_time_to_go", lambda m: 50.0, "default_time_to_go 50.0 lies outside"),
}


@pytest.mark.parametrize("name", list(SEALED_EDITS))
def test_metadata_the_graph_does_not_follow_is_refused_even_when_sealed(exported, tmp_path, name):
    """Values the graph bakes in are checked against the graph, not taken from the metadata on
    trust: a file sealed again after its threshold, problem kind, domain or width was edited is
    refused at load (the digest alone shows only that the file is the one some export wrote)."""
    path = exported[0]
    key, value, message = SEALED_EDITS[name]
    meta = Filter.load(path).metadata
    edits = [_set_metadata(key, value(meta))]
    if name == "width":  # a domain row for the fourth state, so that the graph's own width is what differs
        edits.append(_set_metadata("reach.domain", [*meta.domain, (-1.0, 1.0)]))
    bad = _edited(path, tmp_path / f"{name}.onnx", lambda model: [edit(model) for edit in edits], reseal=True)
    with pytest.raises(ValueError, match=message):
        Filter.load(bad)


def test_a_graph_with_a_fixed_batch_is_refused_naming_it(exported, tmp_path):
    def fix_batch(model):
        for value in [*model.graph.input, *model.graph.output]:
            dims = value.type.tensor_type.shape.dim
            if dims:
                dims[0].dim_value = 4

    bad = _edited(exported[0], tmp_path / "fixed.onnx", fix_batch, reseal=True)
    with pytest.raises(ValueError, match="fixes state's batch dimension to 4; it must be free"):
        Filter.load(bad)


def test_bad_calls_are_one_clear_line_each(exported):
    runtime = Filter.load(exported[0])
    x, u = np.array([[0.1, 0.0, 0.0]], np.float32), np.array([[1.0]], np.float32)
    cases = [
        ((x[:, :2], u), r"states must have shape \(\.\.\., 3\), got \(1, 2\)"),
        ((x, np.ones((1, 2), np.float32)), r"u_nominal must have shape \(\.\.\., 1\), got \(1, 2\)"),
        ((x, u, 10**400), r"t is an integer of 1329 bits"),
        ((x, u, float("inf")), r"t = inf is not a finite number"),
        ((x, u, float("nan")), r"t = nan is not a finite number"),
        ((x, u, np.array([np.inf])), r"t = inf is not a finite number"),
        ((np.zeros((0, 3), np.float32), np.zeros((0, 1), np.float32)), r"an empty batch of states \(shape \(0, 3\)\)"),
    ]
    for args, message in cases:
        with pytest.raises(ValueError, match=message) as caught:
            runtime(*args)
        assert len(str(caught.value).splitlines()) == 1


def test_the_file_records_and_the_command_prints_the_sources_verdict(exported):
    """A shipped model's verdict (its card's), recorded and printed; a user's own value function
    carries none."""
    from training.pretrained import card

    path, stdout = exported
    verdict = card("air3d").verdict
    recorded = Filter.load(path).metadata.source_verdict
    assert recorded == {"passes": verdict.passes, "line": f"pretrained:air3d {verdict.line()}"}
    assert f"trust bar: pretrained:air3d {verdict.line()}" in stdout.splitlines()
    own = source_verdict("runs/mine/model.pt")
    assert own["passes"] is None and "the user's own value function" in own["line"]
    untrusted = source_verdict("pretrained:dubins3d")
    assert untrusted["passes"] is card("dubins3d").verdict.passes is False and "fails" in untrusted["line"]


def test_reach_export_refuses_a_time_to_go_outside_the_range_in_one_line(tmp_path):
    out = tmp_path / "f.onnx"
    done = subprocess.run(
        [sys.executable, "-m", "reach", "export", "pretrained:air3d", "--out", str(out), "--time-to-go", "50"],
        capture_output=True,
        text=True,
        env=ENV,
    )
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "time-to-go 50 lies outside [0, 1.1]" in done.stderr and not out.exists()


def test_the_trace_batch_is_no_inputs_width():
    from reach.systems import make_system

    assert example_batch(make_system("air3d")) == 4  # 3 states, 1 input: as before
    narrow = make_system("narrowpassage")
    assert narrow.control_dim == 4 and example_batch(narrow) not in (narrow.state_dim, narrow.control_dim, 4)
