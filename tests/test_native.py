"""The native engine (reach_runtime.native): each operator compiled to C computes what ONNX Runtime
computes, NaN included; its sine and cosine are accurate; what it cannot compile is refused by name.

The exported filters themselves (Air3D switch, decided by both engines) are checked in
tests/test_export.py, which already exports them."""

from __future__ import annotations

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from reach_runtime.native import NativeGraph, c_source  # noqa: E402

pytestmark = pytest.mark.skipif(
    not any(__import__("shutil").which(c) for c in ("cc", "gcc", "clang")), reason="no C compiler"
)


def _model(nodes, inputs, outputs, initializers=()):
    graph = helper.make_graph(
        nodes,
        "ops",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, s) for n, s in inputs],
        [helper.make_tensor_value_info(n, t, s) for n, t, s in outputs],
        initializer=[numpy_helper.from_array(np.asarray(v), n) for n, v in initializers],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)], ir_version=10)


def _both(model, feeds, tmp_path, name="m.onnx"):
    path = tmp_path / name
    onnx.save(model, path)
    expected = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, feeds)
    got = NativeGraph(path, cache=tmp_path / "cache").run(feeds)
    return expected, got


def test_each_operator_computes_what_onnx_runtime_computes(tmp_path):
    """One graph with every kind of node the compiler emits: elementwise with broadcasting, Where,
    Cast, Clip, NaN-propagating Min/Max, the reductions and ArgMax, slices, transposes, Expand,
    Tile, Concat, Gather and GatherND with computed indices, Gemm with a transposed weight and
    MatMul, on rows with NaN and inf among them."""
    rng = np.random.default_rng(0)
    w = rng.normal(size=(5, 4)).astype(np.float32)  # Gemm's B, transposed (transB)
    m = rng.normal(size=(4, 3)).astype(np.float32)
    bias = rng.normal(size=(5,)).astype(np.float32)
    i64 = lambda *v: np.array(v, np.int64)  # noqa: E731
    nodes = [
        helper.make_node("Gemm", ["x", "w", "bias"], ["g"], transB=1, alpha=0.5, beta=2.0),  # (1, 5)
        helper.make_node("Sin", ["g"], ["s"]),
        helper.make_node("Cos", ["x"], ["c"]),
        helper.make_node("MatMul", ["c", "m"], ["mm"]),  # (1, 3)
        helper.make_node("Slice", ["s", "st", "en", "ax", "sp"], ["sl"]),  # every other column, reversed
        helper.make_node("Min", ["sl", "mm", "half"], ["mn"]),
        helper.make_node("Max", ["mn", "x3"], ["mx"]),
        helper.make_node("Clip", ["mx", "lo", "hi"], ["cl"]),
        helper.make_node("Greater", ["cl", "zero"], ["gt"]),
        helper.make_node("Where", ["gt", "cl", "x3"], ["wh"]),
        helper.make_node("Cast", ["gt"], ["gtf"], to=TensorProto.FLOAT),
        helper.make_node("Add", ["wh", "gtf"], ["ad"]),
        helper.make_node("Unsqueeze", ["ad", "ax0"], ["un"]),  # (1, 1, 3)
        helper.make_node("Expand", ["un", "shape2"], ["ex"]),  # (1, 2, 3)
        helper.make_node("Transpose", ["ex"], ["tr"], perm=[0, 2, 1]),  # (1, 3, 2)
        helper.make_node("Tile", ["tr", "reps"], ["ti"]),  # (1, 3, 4)
        helper.make_node("ReduceMin", ["ti", "ax2"], ["rmin"], keepdims=0),  # (1, 3)
        helper.make_node("ReduceMax", ["x"], ["rmax"], keepdims=1),  # (1, 1): over everything
        helper.make_node("Concat", ["rmin", "rmax", "x"], ["cat"], axis=1),  # (1, 8)
        helper.make_node("ArgMax", ["cat"], ["am"], axis=1, keepdims=1),  # (1, 1) int64
        helper.make_node("Gather", ["cat", "am"], ["ga"], axis=1),  # (1, 1, 1)
        helper.make_node("Squeeze", ["ga", "ax2"], ["gsq"]),  # (1, 1)
        helper.make_node("Concat", ["zi", "am"], ["idx"], axis=1),  # (1, 2): (row 0, argmax)
        helper.make_node("GatherND", ["cat", "idx"], ["gnd"]),  # (1,)
        helper.make_node("Abs", ["cat"], ["ab"]),
        helper.make_node("Sqrt", ["ab"], ["sq"]),
        helper.make_node("Round", ["sq"], ["ro"]),
        helper.make_node("Sign", ["x"], ["sg"]),
        helper.make_node("Equal", ["x", "x"], ["eq"]),
        helper.make_node("Not", ["eq"], ["isnan"]),
        helper.make_node("Cast", ["isnan"], ["isnan_f"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMax", ["isnan_f"], ["anynan"], keepdims=0),  # a scalar flag over the batch
        helper.make_node("Cast", ["anynan"], ["flag"], to=TensorProto.BOOL),
    ]
    inits = [
        ("w", w), ("m", m), ("bias", bias), ("st", i64(-1)), ("en", i64(-9)), ("ax", i64(1)), ("sp", i64(-2)),
        ("half", np.float32(0.5)), ("x3", np.zeros((1, 3), np.float32) - 0.25), ("lo", np.float32(-0.2)),
        ("hi", np.float32(0.9)), ("zero", np.float32(0.0)), ("ax0", i64(1)), ("shape2", i64(1, 2, 3)),
        ("reps", i64(1, 1, 2)), ("ax2", i64(2)), ("zi", np.zeros((1, 1), np.int64)),
    ]  # fmt: skip
    outputs = [
        ("cat", TensorProto.FLOAT, ["b", 8]), ("am", TensorProto.INT64, ["b", 1]), ("gsq", TensorProto.FLOAT, ["b", 1]),
        ("gnd", TensorProto.FLOAT, ["b"]), ("ro", TensorProto.FLOAT, ["b", 8]), ("sg", TensorProto.FLOAT, ["b", 4]),
        ("flag", TensorProto.BOOL, []),
    ]  # fmt: skip
    model = _model(nodes, [("x", ["b", 4])], outputs, inits)
    x = (3 * rng.normal(size=(64, 4))).astype(np.float32)
    x[5, 2] = np.nan
    x[9, 0] = np.inf
    x[11, 3] = -np.inf
    # the graph reduces and gathers over its whole input, so it is run row by row (the compiler's
    # unit); rows with NaN are compared with NumPy's semantics, which ONNX Runtime's reductions
    # and ArgMax do not follow (they may skip a NaN; torch and the native engine do not)
    for r in range(x.shape[0]):
        expected, got = _both(model, {"x": x[r : r + 1]}, tmp_path)
        if np.isnan(x[r]).any():
            expected = _reference(model, {"x": x[r : r + 1]})
            assert np.isnan(got[0][0, 3]) and np.isnan(got[4]).any()  # the NaN reached the reductions
        for name, e, g in zip([o[0] for o in outputs], expected, got):
            assert e.shape == g.shape and e.dtype == g.dtype, name
            np.testing.assert_allclose(g, e, rtol=2e-6, atol=2e-6, err_msg=f"{name}, row {r}")


def _reference(model, feeds):
    """The model's outputs by the NumPy semantics the compiler folds with."""
    from reach_runtime.native.folding import evaluate

    values = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer} | dict(feeds)
    for node in model.graph.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        with np.errstate(all="ignore"):
            values[node.output[0]] = evaluate(node.op_type, attrs, [values[n] if n else None for n in node.input])
    return [np.asarray(values[o.name]) for o in model.graph.output]


def test_a_batch_is_decided_row_by_row_and_its_flag_is_any_row(tmp_path):
    """A scalar boolean output (the filter's ``untrusted``) is the OR over the rows."""
    nodes = [
        helper.make_node("Equal", ["x", "x"], ["eq"]),
        helper.make_node("Not", ["eq"], ["isnan"]),
        helper.make_node("Cast", ["isnan"], ["f"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMax", ["f"], ["m"], keepdims=0),
        helper.make_node("Cast", ["m"], ["flag"], to=TensorProto.BOOL),
        helper.make_node("Sign", ["x"], ["sg"]),
    ]
    model = _model(nodes, [("x", ["b", 3])], [("sg", TensorProto.FLOAT, ["b", 3]), ("flag", TensorProto.BOOL, [])])
    x = np.random.default_rng(2).normal(size=(6, 3)).astype(np.float32)
    expected, got = _both(model, {"x": x}, tmp_path)
    assert not got[1] and not expected[1]
    np.testing.assert_array_equal(got[0], expected[0])
    x[4, 1] = np.nan
    expected, got = _both(model, {"x": x}, tmp_path)
    assert got[1] and expected[1] and np.isnan(got[0][4, 1])  # Sign(NaN) is NaN, not 0
    np.testing.assert_array_equal(got[0], expected[0])


def test_sine_and_cosine_are_accurate_and_propagate_nan(tmp_path):
    model = _model(
        [helper.make_node("Sin", ["x"], ["s"]), helper.make_node("Cos", ["x"], ["c"])],
        [("x", ["b", 1000])],
        [("s", TensorProto.FLOAT, ["b", 1000]), ("c", TensorProto.FLOAT, ["b", 1000])],
    )
    rng = np.random.default_rng(1)
    x = rng.uniform(-8192, 8192, size=(4, 1000)).astype(np.float32)
    x[0] = rng.uniform(-4, 4, 1000)
    x[3, :4] = [np.nan, np.inf, -np.inf, 0.0]
    onnx.save(model, tmp_path / "sin.onnx")
    s, c = NativeGraph(tmp_path / "sin.onnx", cache=tmp_path / "cache").run({"x": x})
    finite = np.isfinite(x)
    assert np.abs(s[finite] - np.sin(x[finite].astype(np.float64))).max() < 1.5e-7
    assert np.abs(c[finite] - np.cos(x[finite].astype(np.float64))).max() < 1.5e-7
    assert np.isnan(s[3, :3]).all() and np.isnan(c[3, :3]).all() and s[3, 3] == 0.0 and c[3, 3] == 1.0


def test_what_cannot_be_compiled_is_refused_by_name(tmp_path, monkeypatch):
    model = _model(
        [helper.make_node("Softsign", ["x"], ["y"])], [("x", ["b", 2])], [("y", TensorProto.FLOAT, ["b", 2])]
    )
    onnx.save(model, tmp_path / "softsign.onnx")
    with pytest.raises(ValueError, match="operators the native compiler does not handle: Softsign"):
        c_source(tmp_path / "softsign.onnx")
    with pytest.raises(ValueError, match="no such file"):
        c_source(tmp_path / "missing.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="not a readable ONNX model"):
        c_source(tmp_path / "junk.onnx")
    scalar = _model(
        [helper.make_node("ReduceMax", ["x"], ["y"], keepdims=0)], [("x", ["b", 2])], [("y", TensorProto.FLOAT, [])]
    )
    onnx.save(scalar, tmp_path / "scalar.onnx")
    with pytest.raises(ValueError, match="output y is a scalar that is not a flag"):
        c_source(tmp_path / "scalar.onnx")
    sin = _model([helper.make_node("Sin", ["x"], ["y"])], [("x", ["b", 2])], [("y", TensorProto.FLOAT, ["b", 2])])
    onnx.save(sin, tmp_path / "sin.onnx")
    with pytest.raises(ValueError, match="function must be a C identifier"):
        c_source(tmp_path / "sin.onnx", function="2fast")
    monkeypatch.setenv("CC", "no-such-compiler-here")
    with pytest.raises(ValueError, match="no-such-compiler-here"):
        NativeGraph(tmp_path / "sin.onnx", cache=tmp_path / "cache")


def test_the_smooth_and_lookahead_operators_compute_what_onnx_runtime_computes(tmp_path):
    """TopK (sorted, ties in index order, both directions), GatherElements with computed indices,
    ReduceSum, ArgMin, and float64 sine, cosine and square root, as the smooth filter's projection
    and the lookahead's rollout use them."""
    i64 = lambda *v: np.array(v, np.int64)  # noqa: E731
    nodes = [
        helper.make_node("TopK", ["x", "k"], ["low", "low_i"], axis=-1, largest=0, sorted=1),
        helper.make_node("TopK", ["x", "k"], ["high", "high_i"], axis=1, largest=1, sorted=1),
        helper.make_node("GatherElements", ["x", "high_i"], ["again"], axis=-1),
        helper.make_node("ReduceSum", ["x", "ax1"], ["total"], keepdims=0),
        helper.make_node("ArgMin", ["x"], ["first_low"], axis=1, keepdims=0),
        helper.make_node("Cast", ["x"], ["x64"], to=TensorProto.DOUBLE),
        helper.make_node("Sin", ["x64"], ["s64"]),
        helper.make_node("Abs", ["x64"], ["a64"]),
        helper.make_node("Sqrt", ["a64"], ["r64"]),
        helper.make_node("Cos", ["r64"], ["c64"]),
        helper.make_node("Add", ["s64", "c64"], ["sc64"]),
    ]
    outputs = [
        ("low", TensorProto.FLOAT, ["b", 3]), ("low_i", TensorProto.INT64, ["b", 3]),
        ("high", TensorProto.FLOAT, ["b", 3]), ("high_i", TensorProto.INT64, ["b", 3]),
        ("again", TensorProto.FLOAT, ["b", 3]), ("total", TensorProto.FLOAT, ["b"]),
        ("first_low", TensorProto.INT64, ["b"]), ("sc64", TensorProto.DOUBLE, ["b", 6]),
    ]  # fmt: skip
    model = _model(nodes, [("x", ["b", 6])], outputs, [("k", i64(3)), ("ax1", i64(1))])
    rng = np.random.default_rng(3)
    x = rng.normal(size=(40, 6)).astype(np.float32)
    x[::3, 4] = x[::3, 1]  # ties: the lower index comes first
    x[::5, :] = 0.5  # a row of equal values
    expected, got = _both(model, {"x": x}, tmp_path)
    for (name, _, _), e, g in zip(outputs, expected, got):
        assert e.shape == g.shape and e.dtype == g.dtype, name
        np.testing.assert_allclose(g, e, rtol=1e-6, atol=1e-6, err_msg=name)


def test_the_other_layers_operators_compute_what_onnx_runtime_computes(tmp_path):
    """What tanh, GELU and ReLU layers and users' own systems export to: Exp, Log, Tanh, Erf, Floor,
    Ceil, Relu, Reciprocal, Sigmoid and Pow, within float32 rounding of ONNX Runtime."""
    ops = ["Exp", "Log", "Tanh", "Erf", "Floor", "Ceil", "Relu", "Reciprocal", "Sigmoid"]
    nodes = [helper.make_node("Abs", ["x"], ["ax"])]
    nodes += [helper.make_node(op, ["ax" if op == "Log" else "x"], [op]) for op in ops]
    nodes.append(helper.make_node("Pow", ["ax", "x"], ["Pow"]))
    outputs = [(op, TensorProto.FLOAT, ["b", 4]) for op in [*ops, "Pow"]]
    model = _model(nodes, [("x", ["b", 4])], outputs)
    x = (3 * np.random.default_rng(4).normal(size=(50, 4))).astype(np.float32)
    expected, got = _both(model, {"x": x}, tmp_path)
    for (name, _, _), e, g in zip(outputs, expected, got):
        np.testing.assert_allclose(g, e, rtol=3e-7, atol=1e-7, err_msg=name)


def test_work_one_side_of_a_flag_reads_runs_only_where_the_flag_is_on(tmp_path):
    """A row's flag gates what only its one side reads (the switch's greedy backup input: read by
    ``Where(intervene, greedy, u*)`` and by ``And(untrusted, intervene)``). The gated work sits
    inside ``if`` in the C source, and the outputs equal ONNX Runtime's on both sides: a NaN in the
    gated work counts only where the flag is on. An ``And`` of two flags gates the later by the
    earlier, never each by the other (the first version did, and decided from stale values)."""
    from reach_runtime.native.emission import emitter_for

    f = TensorProto.FLOAT
    nodes = [
        helper.make_node("ReduceSum", ["x", "axis"], ["s"], keepdims=1),  # (b, 1)
        helper.make_node("Greater", ["s", "zero"], ["on"]),  # the row's flag
        helper.make_node("Log", ["x"], ["lg"]),  # the gated work: NaN for a negative entry
        helper.make_node("Mul", ["lg", "two"], ["work"]),
        helper.make_node("Where", ["on", "work", "x"], ["out"]),
        helper.make_node("Equal", ["work", "work"], ["same"]),
        helper.make_node("Not", ["same"], ["nan"]),
        helper.make_node("Cast", ["nan"], ["nanf"], to=f),
        helper.make_node("ReduceMax", ["nanf", "axis"], ["row_nan"], keepdims=1),
        helper.make_node("Cast", ["row_nan"], ["row_bad"], to=TensorProto.BOOL),
        helper.make_node("And", ["row_bad", "on"], ["bad"]),  # counts only where the flag is on
        helper.make_node("Cast", ["bad"], ["badf"], to=f),
        helper.make_node("ReduceMax", ["badf"], ["any"], keepdims=0),
        helper.make_node("Cast", ["any"], ["untrusted"], to=TensorProto.BOOL),
        helper.make_node("Greater", ["s", "one"], ["high"]),  # two flags read only by their And
        helper.make_node("Less", ["s", "five"], ["low"]),
        helper.make_node("And", ["high", "low"], ["both"]),
    ]
    model = _model(
        nodes,
        [("x", ["b", 3])],
        [("out", f, ["b", 3]), ("untrusted", TensorProto.BOOL, []), ("both", TensorProto.BOOL, ["b", 1])],
        [
            ("axis", np.array([1], np.int64)),
            ("zero", np.float32(0)),
            ("one", np.float32(1)),
            ("two", np.float32(2)),
            ("five", np.float32(5)),
        ],
    )
    onnx.save(model, tmp_path / "gate.onnx")
    assert emitter_for(tmp_path / "gate.onnx").gated >= 8
    source = c_source(tmp_path / "gate.onnx")
    gated = source[source.index("if (") :]
    assert "logf(" in gated.split("}")[0]  # the logarithm runs inside the flag's block
    x = np.array([[1, 2, 3], [-1, -2, 0.5], [2, 1, 0.5], [0.2, 0.3, 0.1]], np.float32)
    expected, got = _both(model, {"x": x}, tmp_path)
    assert not expected[1] and not got[1]  # row 1's NaN is off its flag
    for e, g in zip(expected, got):
        np.testing.assert_array_equal(g, e)
    x[3, 0] = -0.1  # its sum stays positive: a NaN where the flag is on
    expected, got = _both(model, {"x": x}, tmp_path, "gate2.onnx")
    assert expected[1] and got[1]
    for e, g in zip(expected[:1] + expected[2:], got[:1] + got[2:]):
        np.testing.assert_array_equal(g, e)
