"""An exported filter compiled to straight-line C: one decision at control-loop rate, no graph runtime.

ONNX Runtime spends about a microsecond dispatching each node of a graph, and an exported filter's
decision is several hundred nodes (the network, its input gradient, the failure margin's autograd,
the backup input's candidates). At batch 1 that dispatch, not the arithmetic, is the latency. This
module turns the graph into one C function instead:

- every tensor's shape is fixed by a batch of one state, so shapes, ``Shape``/``Reshape``
  arithmetic and every node that depends only on constants are evaluated here, once, with NumPy;
- each remaining node becomes a loop over static buffers; data movement (slices, transposes,
  broadcasts, gathers with fixed indices) becomes copies through index tables computed by running
  the same NumPy operation on the positions of its input;
- the weights become ``static const`` arrays;
- work that only one side of a row's flag reads runs inside ``if`` on that flag (the switch's
  greedy backup input only where it intervenes: :meth:`_Emitter._gate_branches`).

A batch is decided row by row: the graph decides each state on its own, and its scalar
``untrusted`` flag is the OR over the rows. :func:`c_source` writes the C file (to compile into a
controller: it needs only ``<math.h>`` and ``<stdint.h>``), and :func:`compile_filter` builds it
into a shared library with the system's C compiler, cached by the source's hash.
``reach_runtime.Filter.load(path, engine="native")`` runs that library behind the same checks as
the ONNX Runtime engine.

NaN and inf propagate (no ``-ffast-math``), so the graph's own non-finite checks raise
``untrusted`` here too. Elementwise ``Min``, ``Max``, ``Clip`` and ``Sign`` return NaN for a NaN
operand, as ONNX Runtime does. The reductions return NaN where any operand is NaN and ``ArgMax``
picks a NaN, as torch (whose operations the graph was traced from) and NumPy do; ONNX Runtime's
``ReduceMin``/``ReduceMax`` return NaN only where the NaN comes first, and its ``ArgMax`` skips it.
Float sums (matrix products) run in another order than ONNX Runtime's, so
values agree to float32 rounding, not bit for bit.

Reading the graph needs the ``onnx`` package; running the compiled library needs only the C
compiler that built it, NumPy and ``ctypes``. An operator outside the set exported filters use is
refused, naming it.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import json
import math
import os
import shutil
import subprocess
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["STATUS", "SUPPORTED_OPS", "NativeGraph", "c_source", "compile_filter"]

#: ONNX element types the compiler handles, as NumPy dtypes and C types
_DTYPES = {
    1: np.dtype(np.float32), 6: np.dtype(np.int32), 7: np.dtype(np.int64), 9: np.dtype(np.bool_),
    11: np.dtype(np.float64),
}  # fmt: skip
_CTYPES = {"float32": "float", "int32": "int32_t", "int64": "int64_t", "bool": "unsigned char", "float64": "double"}

#: elementwise operators: the C expression of their operands a, b (c: Where's condition)
_UNARY = {
    "Abs": "RABS({a})", "Neg": "(-{a})", "Sin": "rsin_q({a}, 0.0f)", "Cos": "rsin_q({a}, 1.0f)", "Sqrt": "sqrtf({a})",
    "Round": "rintf({a})", "Sign": "(({a}) != ({a}) ? ({a}) : (({a}) > 0) - (({a}) < 0))", "Not": "(!{a})",
    "Identity": "{a}", "Exp": "expf({a})", "Log": "logf({a})", "Tanh": "tanhf({a})", "Erf": "erff({a})",
    "Floor": "floorf({a})", "Ceil": "ceilf({a})", "Relu": "RMAX({a}, 0)", "Reciprocal": "(1 / ({a}))",
    "Sigmoid": "(1 / (1 + expf(-({a}))))",
}  # fmt: skip
_BINARY = {
    "Add": "{a} + {b}", "Sub": "{a} - {b}", "Mul": "{a} * {b}", "Div": "{a} / {b}",
    "Equal": "{a} == {b}", "Greater": "{a} > {b}", "Less": "{a} < {b}", "GreaterOrEqual": "{a} >= {b}",
    "LessOrEqual": "{a} <= {b}", "And": "{a} && {b}", "Or": "{a} || {b}",
    "Max": "RMAX({a}, {b})", "Min": "RMIN({a}, {b})", "Pow": "powf({a}, {b})",
}  # fmt: skip
#: unary operators whose C functions are float32 ones
_FLOAT_ONLY = {"Sin", "Cos", "Sqrt", "Round", "Exp", "Log", "Tanh", "Erf", "Floor", "Ceil", "Sigmoid"}
#: the same in float64 (the smooth filter's projection is solved in float64): the C library's own
_DOUBLE = {
    "Sin": "sin({a})", "Cos": "cos({a})", "Sqrt": "sqrt({a})", "Round": "rint({a})", "Exp": "exp({a})",
    "Log": "log({a})", "Tanh": "tanh({a})", "Erf": "erf({a})", "Floor": "floor({a})", "Ceil": "ceil({a})",
    "Sigmoid": "(1 / (1 + exp(-({a}))))", "Pow": "pow({a}, {b})",
}  # fmt: skip
_MOVES = {"Slice", "Transpose", "Expand", "Tile", "Reshape", "Squeeze", "Unsqueeze", "Identity", "Gather", "GatherND"}
#: reductions: how an accumulator m takes in the next operand v
_REDUCTIONS = {"ReduceMin": "RMIN({m}, {v})", "ReduceMax": "RMAX({m}, {v})", "ReduceSum": "{m} + {v}"}

#: every operator the compiler reads (what exported filters are made of)
SUPPORTED_OPS = frozenset(
    set(_UNARY) | set(_BINARY) | _MOVES | set(_REDUCTIONS)
    | {"Where", "Cast", "Clip", "Concat", "Gemm", "MatMul", "ArgMax", "ArgMin", "Shape", "Constant", "Range"}
    | {"GatherElements", "TopK"}
)  # fmt: skip

_PRELUDE = """\
#include <math.h>
#include <stdint.h>
#include <string.h>
/* NaN-propagating minimum and maximum, as ONNX Runtime's Min, Max, Clip and reductions */
#define RMIN(a, b) (((a) < (b) || (a) != (a)) ? (a) : (b))
#define RMAX(a, b) (((a) > (b) || (a) != (a)) ? (a) : (b))
#define RABS(a) ((a) < 0 ? -(a) : (a))
/* sin(x + shift * pi / 2) in float32, branch-free so that loops over it vectorise (the C library's
   sinf is a call per element, which at batch 1 is most of a decision's time): x = k pi/2 + r with
   pi/2 in three parts (Cody and Waite), then a minimax polynomial of sin or cos of r (Cephes'
   coefficients) by the quadrant. Within 1e-7 of sin for |x| <= 8192 (tests/test_native.py); NaN
   and inf give NaN, as sinf does. */
static inline float rsin_q(float x, float shift) {
  float k = rintf(x * 0.636619772367581343f);
  float r = x - k * 1.5703125f;
  r = r - k * 4.837512969970703125e-4f;
  r = r - k * 7.54978995489188216e-8f;
  float q = k + shift;
  q = q - 4.0f * floorf(q * 0.25f);
  float z = r * r;
  float s = r + r * z * (-1.6666654611e-1f + z * (8.3321608736e-3f + z * -1.9515295891e-4f));
  float c = 1.0f - 0.5f * z
            + z * z * (4.166664568298827e-2f + z * (-1.388731625493765e-3f + z * 2.443315711809948e-5f));
  float odd = q - 2.0f * floorf(q * 0.5f);
  float v = odd != 0.0f ? c : s;
  return q >= 2.0f ? -v : v;
}
"""


# ---------------------------------------------------------------------------------------------
# NumPy semantics of each operator (shapes and constants are folded with these)
def _attrs(node: Any) -> dict[str, Any]:
    import onnx  # lazy: reading the graph is the only use of onnx, and running needs none

    return {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}


def _axes(values: Any, rank: int) -> tuple[int, ...]:
    return tuple(int(a) % rank for a in np.asarray(values).reshape(-1))


def _evaluate(op: str, attrs: dict[str, Any], xs: list[np.ndarray | None]) -> np.ndarray:
    """One node's output, in NumPy (the reference the C code is generated from and checked against)."""
    a = xs[0]
    if op in _UNARY:
        fn = {
            "Abs": np.abs, "Neg": np.negative, "Sin": np.sin, "Cos": np.cos, "Sqrt": np.sqrt, "Round": np.round,
            "Sign": np.sign, "Not": np.logical_not, "Identity": np.array, "Exp": np.exp, "Log": np.log,
            "Tanh": np.tanh, "Erf": np.vectorize(math.erf, otypes=[np.float64]), "Floor": np.floor, "Ceil": np.ceil,
            "Relu": lambda v: np.where(v < 0, 0, v), "Reciprocal": np.reciprocal,
            "Sigmoid": lambda v: 1 / (1 + np.exp(-v)),
        }[op]  # fmt: skip
        return np.asarray(fn(a)).astype(a.dtype, copy=False)
    if op in ("Max", "Min"):
        return functools.reduce(np.maximum if op == "Max" else np.minimum, xs)
    if op in _BINARY:
        b = xs[1]
        if op == "Div" and a.dtype.kind in "iu":
            return np.trunc(a / b).astype(a.dtype)
        fn = {
            "Add": np.add, "Sub": np.subtract, "Mul": np.multiply, "Div": np.divide, "Equal": np.equal,
            "Greater": np.greater, "Less": np.less, "GreaterOrEqual": np.greater_equal, "LessOrEqual": np.less_equal,
            "And": np.logical_and, "Or": np.logical_or, "Pow": np.power,
        }[op]  # fmt: skip
        out = np.asarray(fn(a, b))
        return out if out.dtype == np.bool_ else out.astype(a.dtype, copy=False)
    if op == "Where":
        return np.where(a, xs[1], xs[2])
    if op == "Cast":
        return a.astype(_DTYPES[attrs["to"]])
    if op == "Clip":
        out = a
        if len(xs) > 1 and xs[1] is not None:
            out = np.maximum(out, xs[1])
        if len(xs) > 2 and xs[2] is not None:
            out = np.minimum(out, xs[2])
        return out.astype(a.dtype, copy=False)
    if op == "Shape":
        return np.array(a.shape[attrs.get("start", 0) : attrs.get("end")], dtype=np.int64)
    if op == "Squeeze":
        axes = _axes(xs[1], a.ndim) if len(xs) > 1 and xs[1] is not None else None
        return np.squeeze(a, axis=axes)
    if op == "Unsqueeze":
        rank = a.ndim + np.asarray(xs[1]).size
        out = a
        for axis in sorted(_axes(xs[1], rank)):
            out = np.expand_dims(out, axis)
        return out
    if op == "Reshape":
        shape = [int(s) for s in xs[1]]
        if not attrs.get("allowzero", 0):
            shape = [a.shape[i] if s == 0 else s for i, s in enumerate(shape)]
        return a.reshape(shape)
    if op == "Slice":
        starts, ends = np.asarray(xs[1]), np.asarray(xs[2])
        axes = _axes(xs[3], a.ndim) if len(xs) > 3 and xs[3] is not None else tuple(range(starts.size))
        steps = np.asarray(xs[4]) if len(xs) > 4 and xs[4] is not None else np.ones(starts.size, np.int64)
        index = [slice(None)] * a.ndim
        for axis, start, end, step in zip(axes, starts, ends, steps):
            index[axis] = slice(int(start), int(end), int(step))
        return a[tuple(index)]
    if op == "Transpose":
        return np.transpose(a, attrs.get("perm"))
    if op == "Expand":
        return np.broadcast_to(a, np.broadcast_shapes(a.shape, tuple(int(s) for s in xs[1]))).copy()
    if op == "Tile":
        return np.tile(a, tuple(int(r) for r in xs[1]))
    if op == "Concat":
        return np.concatenate(xs, axis=attrs["axis"])
    if op == "Gather":
        return np.take(a, xs[1], axis=attrs.get("axis", 0))
    if op == "GatherND":
        indices = np.asarray(xs[1])
        return a[tuple(np.moveaxis(indices, -1, 0))]
    if op in _REDUCTIONS:
        axes = xs[1] if len(xs) > 1 and xs[1] is not None else attrs.get("axes")
        if axes is None or np.asarray(axes).size == 0:
            if attrs.get("noop_with_empty_axes", 0):
                return a.copy()
            axis = None
        else:
            axis = _axes(axes, a.ndim)
        fn = {"ReduceMin": np.min, "ReduceMax": np.max, "ReduceSum": np.sum}[op]
        return np.asarray(fn(a, axis=axis, keepdims=bool(attrs.get("keepdims", 1)))).astype(a.dtype, copy=False)
    if op in ("ArgMax", "ArgMin"):
        axis = attrs.get("axis", 0) % a.ndim
        out = (np.argmax if op == "ArgMax" else np.argmin)(a, axis=axis).astype(np.int64)
        return np.expand_dims(out, axis) if attrs.get("keepdims", 1) else out
    if op == "Range":
        return np.arange(a, xs[1], xs[2]).astype(a.dtype)
    if op == "GatherElements":
        axis = attrs.get("axis", 0) % a.ndim
        indices = np.where(xs[1] < 0, xs[1] + a.shape[axis], xs[1])
        return np.take_along_axis(a, indices, axis=axis)
    if op == "TopK":
        axis = attrs.get("axis", -1) % a.ndim
        k = int(np.asarray(xs[1]).reshape(-1)[0])
        # ties keep the lower index first (the ONNX rule): a stable sort, of -a for the largest
        order = np.argsort(-a if attrs.get("largest", 1) else a, axis=axis, kind="stable")
        indices = np.take(order, np.arange(k), axis=axis).astype(np.int64)
        return np.take_along_axis(a, indices, axis=axis), indices
    if op == "Gemm":
        left = a.T if attrs.get("transA", 0) else a
        right = xs[1].T if attrs.get("transB", 0) else xs[1]
        out = attrs.get("alpha", 1.0) * (left @ right)
        if len(xs) > 2 and xs[2] is not None:
            out = out + attrs.get("beta", 1.0) * xs[2]
        return out.astype(a.dtype)
    if op == "MatMul":
        return np.matmul(a, xs[1])
    raise ValueError(f"operator {op} is not one the native compiler handles")


# ---------------------------------------------------------------------------------------------
@dataclass
class _Tensor:
    name: str
    value: np.ndarray  # its value at batch 1 for a constant; zeros of its shape and dtype otherwise
    constant: bool
    c_name: str = ""

    @property
    def ctype(self) -> str:
        return _CTYPES[self.value.dtype.name]


def _strided(index: np.ndarray) -> str | None:
    """The index map as arithmetic on the output position ``i``, where it is a strided view of its
    input (a broadcast, slice, transpose or reshape): ``offset + sum_k ((i / P_k) % S_k) * T_k``
    over at most three merged axes. None where it is not (a tile, a gather): a table then."""
    shape = index.shape
    if index.ndim == 0 or index.size < 2:
        return None
    # merge axes that run contiguously in the input, and drop axes of length 1
    offset = int(index.reshape(-1)[0])
    axes: list[tuple[int, int]] = []  # (length, input stride), outermost first
    for k, length in enumerate(shape):
        if length == 1:
            continue
        at = [0] * index.ndim
        at[k] = 1
        stride = int(index[tuple(at)]) - offset
        if axes and axes[-1][1] == stride * length:
            axes[-1] = (axes[-1][0] * length, stride)
        else:
            axes.append((length, stride))
    if len(axes) > 3:
        return None
    terms, expected, period = [], np.full(index.size, offset, dtype=np.int64), 1
    position = np.arange(index.size, dtype=np.int64)
    for length, stride in reversed(axes):
        if stride:
            expected += (position // period % length) * stride
            term = "i" if period == 1 else f"(i / {period})"
            if period * length != index.size:
                term = f"({term} % {length})"
            terms.append(term if stride == 1 else f"{term} * {stride}")
        period *= length
    if not np.array_equal(expected, index.reshape(-1)):
        return None
    if offset:
        terms.insert(0, str(offset))
    return " + ".join(terms) if terms else "0"


def _literal(v: Any, dtype: np.dtype) -> str:
    if dtype.kind == "f":
        f = float(v)
        if np.isnan(f):
            return "NAN"
        if np.isinf(f):
            return "INFINITY" if f > 0 else "-INFINITY"
        # the shortest decimal that reads back to the same float32 (or float64)
        return (str(np.float32(f)) + "f") if dtype == np.float32 else repr(f)
    if dtype.kind == "b":
        return "1" if v else "0"
    return f"{int(v)}LL" if dtype == np.int64 else str(int(v))


def _array_literal(values: np.ndarray) -> str:
    flat = values.reshape(-1)
    return "{" + ",".join(_literal(v, values.dtype) for v in flat) + "}"


class _Emitter:
    """Turns the graph, folded at batch 1, into C statements over static buffers."""

    def __init__(self, model: Any, where: str) -> None:
        from onnx import numpy_helper  # lazy: reading the graph is the only use of onnx (running needs none)

        self.metadata: dict[str, str] = {}  # the model's metadata properties (set by _emitter_for)
        graph = model.graph
        self.where = where
        self.tensors: dict[str, _Tensor] = {}
        self.decls: list[str] = []
        self.body: list[str] = []
        self._count = 0
        self._constants: dict[tuple[str, str], str] = {}
        for init in graph.initializer:
            self.tensors[init.name] = _Tensor(init.name, numpy_helper.to_array(init), True)
        self.inputs: list[_Tensor] = []
        for value in graph.input:
            if value.name in self.tensors:
                continue
            dtype = _DTYPES.get(value.type.tensor_type.elem_type)
            dims = [d.dim_value if d.HasField("dim_value") else 1 for d in value.type.tensor_type.shape.dim]
            if dtype is None:
                raise ValueError(f"{where}: input {value.name} has an element type the native compiler does not handle")
            tensor = _Tensor(value.name, np.zeros(dims, dtype), False, f"in_{len(self.inputs)}")
            self.tensors[value.name] = tensor
            self.inputs.append(tensor)
        unsupported = sorted({n.op_type for n in graph.node} - SUPPORTED_OPS)
        if unsupported:
            raise ValueError(f"{where}: operators the native compiler does not handle: {', '.join(unsupported)}")
        self._emitted: list[tuple[Any, int, int]] = []  # (node, first body line, end) of each emitted node
        for node in graph.node:
            start = len(self.body)
            self._node(node)
            if len(self.body) > start:
                self._emitted.append((node, start, len(self.body)))
        self.outputs = [self.tensors[o.name] for o in graph.output]
        self.gated = self._gate_branches({o.name for o in graph.output})

    # -------------------------------------------------------------- naming and storage
    def _new(self, prefix: str) -> str:
        self._count += 1
        return f"{prefix}{self._count}"

    def _c(self, tensor: _Tensor) -> str:
        """The C name of a tensor, emitting a constant's array on first use (once per distinct
        content: a lookahead's backup steps fold the same weights many times over)."""
        if not tensor.c_name:
            values = np.ascontiguousarray(tensor.value).reshape(-1)
            key = (values.dtype.str, hashlib.sha256(values.tobytes()).hexdigest())
            if key in self._constants:
                tensor.c_name = self._constants[key]
                return tensor.c_name
            tensor.c_name = self._constants[key] = self._new("k")
            self.decls.append(
                f"static const {tensor.ctype} {tensor.c_name}[{max(values.size, 1)}] = "
                f"{_array_literal(values if values.size else np.zeros(1, values.dtype))};"
            )
        return tensor.c_name

    def _buffer(self, tensor: _Tensor) -> str:
        tensor.c_name = self._new("t")
        self.decls.append(f"static {tensor.ctype} {tensor.c_name}[{max(tensor.value.size, 1)}];")
        return tensor.c_name

    def _index_table(self, index: np.ndarray) -> str:
        """``name[i]`` for a static index table, or ``i`` / a constant where the table is one."""
        flat = np.asarray(index, dtype=np.int64).reshape(-1)
        if flat.size and np.array_equal(flat, np.arange(flat.size)):
            return "i"
        if flat.size and (flat == flat[0]).all():
            return str(int(flat[0]))
        strided = _strided(np.asarray(index, dtype=np.int64))
        if strided is not None:
            return strided
        return f"{self._table(flat)}[i]"

    def _table(self, values: np.ndarray) -> str:
        """A static index table (int32 where the positions allow), shared by equal tables."""
        flat = np.asarray(values, dtype=np.int64).reshape(-1)
        small = flat.size == 0 or (flat.min(initial=0) >= -(2**31) and flat.max(initial=0) < 2**31)
        return self._c(_Tensor("table", flat.astype(np.int32 if small else np.int64), True))

    # -------------------------------------------------------------- nodes
    def _node(self, node: Any) -> None:
        op = node.op_type
        attrs = _attrs(node)
        if op == "Constant":
            from onnx import numpy_helper  # lazy: reading the graph is the only use of onnx

            value = next(a for a in node.attribute if a.name == "value")
            self.tensors[node.output[0]] = _Tensor(node.output[0], numpy_helper.to_array(value.t), True)
            return
        ins = [self.tensors[name] if name else None for name in node.input]
        values = [t.value if t is not None else None for t in ins]
        try:
            with np.errstate(all="ignore"):  # folding may divide by zero exactly as the graph would
                out_value = _evaluate(op, attrs, values)
        except Exception as error:  # a shape or type the NumPy semantics refuse names the node
            raise ValueError(
                f"{self.where}: node {node.name or op} ({op}) cannot be evaluated at batch 1: {error}"
            ) from None
        values_out = out_value if isinstance(out_value, tuple) else (out_value,)
        if len([name for name in node.output if name]) > len(values_out):
            raise ValueError(f"{self.where}: node {node.name or op} ({op}) has more outputs than it computes")
        outs = [_Tensor(name, np.asarray(v), True) for name, v in zip(node.output, values_out)]
        for t in outs:
            self.tensors[t.name] = t
        dynamic = [t for t in ins if t is not None and not t.constant]
        if op == "Shape" or not dynamic:
            return  # folded: its value is known here
        for t in outs:
            t.constant = False
            t.value = np.zeros(t.value.shape, t.value.dtype)
        if op == "TopK":
            self._emit_topk(attrs, ins, outs)
            return
        if op == "Range":
            raise ValueError(f"{self.where}: Range over computed bounds is not handled")
        getattr(self, f"_emit_{self._family(op)}")(op, attrs, ins, outs[0])

    @staticmethod
    def _family(op: str) -> str:
        if op in _UNARY or op in _BINARY or op in ("Where", "Cast", "Clip"):
            return "elementwise"
        if op in ("Gather", "GatherND"):
            return "gather"
        if op in _MOVES:
            return "move"
        families = {"Concat": "concat", "Gemm": "gemm", "MatMul": "matmul", "ArgMax": "argmax", "ArgMin": "argmax"}
        return families.get(op, "gather_elements" if op == "GatherElements" else "reduce")

    def _operand(self, tensor: _Tensor, shape: tuple[int, ...]) -> str:
        """``name[index]`` reading ``tensor`` broadcast to ``shape`` at output position ``i``."""
        positions = np.arange(tensor.value.size).reshape(tensor.value.shape)
        return f"{self._c(tensor)}[{self._index_table(np.broadcast_to(positions, shape))}]"

    def _emit_elementwise(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        shape = out.value.shape
        name = self._buffer(out)
        if op == "Where":
            c, a, b = (self._operand(t, shape) for t in ins)  # type: ignore[arg-type]
            expr = f"{c} ? {a} : {b}"
        elif op == "Cast":
            a = self._operand(ins[0], shape)  # type: ignore[arg-type]
            expr = f"({a} != 0)" if out.value.dtype == np.bool_ else f"({out.ctype})({a})"
        elif op == "Clip":
            expr = self._operand(ins[0], shape)  # type: ignore[arg-type]
            if len(ins) > 1 and ins[1] is not None:
                expr = f"RMAX({expr}, {self._operand(ins[1], shape)})"
            if len(ins) > 2 and ins[2] is not None:
                expr = f"RMIN({expr}, {self._operand(ins[2], shape)})"
        elif op in ("Max", "Min") and len(ins) != 2:
            expr = self._operand(ins[0], shape)  # type: ignore[arg-type]
            for t in ins[1:]:
                expr = f"R{op.upper()}({expr}, {self._operand(t, shape)})"  # type: ignore[arg-type]
        elif op in _UNARY:
            template = _UNARY[op]
            if op in _FLOAT_ONLY and out.value.dtype == np.float64:
                template = _DOUBLE[op]
            elif op in _FLOAT_ONLY and out.value.dtype != np.float32:
                raise ValueError(f"{self.where}: {op} on {out.value.dtype} is not handled")
            expr = template.format(a=self._operand(ins[0], shape))  # type: ignore[arg-type]
        else:
            template = _BINARY[op]
            if op == "Pow" and out.value.dtype != np.float32:
                if out.value.dtype != np.float64:
                    raise ValueError(f"{self.where}: Pow on {out.value.dtype} is not handled")
                template = _DOUBLE["Pow"]
            expr = template.format(a=self._operand(ins[0], shape), b=self._operand(ins[1], shape))  # type: ignore[arg-type]
        self.body.append(f"for (i = 0; i < {out.value.size}; ++i) {name}[i] = ({out.ctype})({expr});")

    def _emit_move(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        """Data movement: the output's positions of the input, by the same op on the input's positions."""
        source = ins[0]
        assert source is not None and not source.constant
        if any(t is not None and not t.constant for t in ins[1:]):
            raise ValueError(f"{self.where}: {op} with a computed shape or index is not handled")
        positions = np.arange(source.value.size, dtype=np.int64).reshape(source.value.shape)
        with np.errstate(all="ignore"):
            moved = _evaluate(op, attrs, [positions, *[t.value if t is not None else None for t in ins[1:]]])
        name = self._buffer(out)
        self.body.append(
            f"for (i = 0; i < {out.value.size}; ++i) {name}[i] = {source.c_name}[{self._index_table(moved)}];"
        )

    def _emit_gather(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        data, indices = ins[0], ins[1]
        assert data is not None and indices is not None
        if indices.constant:
            if data.constant:
                return
            self._emit_move(op, attrs, ins, out)
            return
        if op == "GatherND" and attrs.get("batch_dims", 0):
            raise ValueError(f"{self.where}: GatherND with batch_dims is not handled")
        src = self._c(data)
        name = self._buffer(out)
        dims = data.value.shape
        idx = indices.c_name
        if op == "Gather":
            axis = attrs.get("axis", 0) % data.value.ndim
            outer = int(np.prod(dims[:axis], dtype=np.int64))
            inner = int(np.prod(dims[axis + 1 :], dtype=np.int64))
            count = indices.value.size
            self.body.append(
                f"for (i = 0; i < {outer}; ++i) for (long q = 0; q < {count}; ++q) {{ long j = (long){idx}[q]; "
                f"if (j < 0) j += {dims[axis]}; if (j < 0 || j >= {dims[axis]}) return 2; "
                f"for (long r = 0; r < {inner}; ++r) "
                f"{name}[(i * {count} + q) * {inner} + r] = {src}[(i * {dims[axis]} + j) * {inner} + r]; }}"
            )
            return
        k = indices.value.shape[-1]
        strides = [int(np.prod(dims[j + 1 :], dtype=np.int64)) for j in range(k)]
        piece = int(np.prod(dims[k:], dtype=np.int64))
        count = indices.value.size // max(k, 1)
        offset = " ".join(
            f"{{ long j = (long){idx}[q * {k} + {j}]; if (j < 0) j += {dims[j]}; "
            f"if (j < 0 || j >= {dims[j]}) return 2; off += j * {strides[j]}; }}"
            for j in range(k)
        )
        self.body.append(
            f"for (long q = 0; q < {count}; ++q) {{ long off = 0; {offset} "
            f"for (long r = 0; r < {piece}; ++r) {name}[q * {piece} + r] = {src}[off + r]; }}"
        )

    def _emit_concat(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        name = self._buffer(out)
        sizes = [t.value.size for t in ins]  # type: ignore[union-attr]
        starts = np.cumsum([0, *sizes])
        tagged = [starts[k] + np.arange(t.value.size, dtype=np.int64).reshape(t.value.shape) for k, t in enumerate(ins)]  # type: ignore[union-attr]
        placed = np.concatenate(tagged, axis=attrs["axis"]).reshape(-1)
        for k, t in enumerate(ins):
            assert t is not None
            where = np.nonzero((placed >= starts[k]) & (placed < starts[k + 1]))[0]
            source = placed[where] - starts[k]
            self.body.append(
                f"for (i = 0; i < {where.size}; ++i) "
                f"{name}[{self._index_table(where)}] = {self._c(t)}[{self._index_table(source)}];"
            )

    def _emit_reduce(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        source = ins[0]
        assert source is not None
        if len(ins) > 1 and ins[1] is not None and not ins[1].constant:
            raise ValueError(f"{self.where}: {op} over computed axes is not handled")
        axes = ins[1].value if len(ins) > 1 and ins[1] is not None else attrs.get("axes")
        shape = source.value.shape
        if axes is None or np.asarray(axes).size == 0:
            if attrs.get("noop_with_empty_axes", 0):
                self._emit_move("Identity", {}, [source], out)
                return
            reduced = tuple(range(len(shape)))
        else:
            reduced = tuple(sorted(_axes(axes, len(shape))))
        kept = tuple(d for d in range(len(shape)) if d not in reduced)
        groups = np.transpose(np.arange(source.value.size).reshape(shape), kept + reduced).reshape(out.value.size, -1)
        name = self._buffer(out)
        table = self._index_table_2d(groups)
        combine = _REDUCTIONS[op]
        self.body.append(
            f"for (i = 0; i < {out.value.size}; ++i) {{ {out.ctype} m = {source.c_name}[{table.format(g=0)}]; "
            f"for (long g = 1; g < {groups.shape[1]}; ++g) "
            f"m = {combine.format(m='m', v=source.c_name + '[' + table.format(g='g') + ']')}; "
            f"{name}[i] = m; }}"
        )

    def _emit_argmax(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        source = ins[0]
        assert source is not None
        if attrs.get("select_last_index", 0):
            raise ValueError(f"{self.where}: {op} with select_last_index is not handled")
        axis = attrs.get("axis", 0) % source.value.ndim
        positions = np.moveaxis(np.arange(source.value.size).reshape(source.value.shape), axis, -1)
        groups = positions.reshape(-1, source.value.shape[axis])
        name = self._buffer(out)
        table = self._index_table_2d(groups)
        # the first largest (smallest), a NaN counting as both, as NumPy and torch pick it
        better = "v > m" if op == "ArgMax" else "v < m"
        self.body.append(
            f"for (i = 0; i < {out.value.size}; ++i) {{ long best = 0; "
            f"{source.ctype} m = {source.c_name}[{table.format(g=0)}]; "
            f"for (long g = 1; g < {groups.shape[1]}; ++g) {{ "
            f"{source.ctype} v = {source.c_name}[{table.format(g='g')}]; "
            f"if (m == m && ({better} || v != v)) {{ m = v; best = g; }} }} {name}[i] = best; }}"
        )

    def _emit_gather_elements(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        """``out[..., j, ...] = data[..., index[..., j, ...], ...]`` along ``axis``: the position with
        the axis coordinate set to 0 (strided) plus the index times the axis stride."""
        data, indices = ins[0], ins[1]
        assert data is not None and indices is not None
        if indices.constant:
            self._emit_move(op, attrs, ins, out)
            return
        axis = attrs.get("axis", 0) % data.value.ndim
        dims = data.value.shape
        stride = int(np.prod(dims[axis + 1 :], dtype=np.int64))
        origin = np.ravel_multi_index(
            tuple(np.zeros_like(c) if k == axis else c for k, c in enumerate(np.indices(out.value.shape))), dims
        )
        name = self._buffer(out)
        self.body.append(
            f"for (i = 0; i < {out.value.size}; ++i) {{ long j = (long){indices.c_name}[i]; "
            f"if (j < 0) j += {dims[axis]}; if (j < 0 || j >= {dims[axis]}) return 2; "
            f"{name}[i] = {self._c(data)}[{self._index_table(origin)} + j * {stride}]; }}"
        )

    def _emit_topk(self, attrs: dict[str, Any], ins: list[_Tensor | None], outs: list[_Tensor]) -> None:
        """The k smallest (largest) along ``axis``, sorted, ties in index order: a stable insertion
        sort of each group's positions (groups are a handful of breakpoints in exported filters)."""
        source, k_input = ins[0], ins[1]
        assert source is not None and k_input is not None
        if not k_input.constant:
            raise ValueError(f"{self.where}: TopK with a computed k is not handled")
        if not attrs.get("sorted", 1):
            raise ValueError(f"{self.where}: TopK unsorted is not handled")
        axis = attrs.get("axis", -1) % source.value.ndim
        n = source.value.shape[axis]
        k = int(np.asarray(k_input.value).reshape(-1)[0])
        before = "w < u" if not attrs.get("largest", 1) else "w > u"
        groups = np.moveaxis(np.arange(source.value.size).reshape(source.value.shape), axis, -1).reshape(-1, n)
        placed = np.moveaxis(np.arange(outs[0].value.size).reshape(outs[0].value.shape), axis, -1).reshape(-1, k)
        read, write = self._index_table_2d(groups), self._index_table_2d(placed)
        values = self._buffer(outs[0])
        positions = self._buffer(outs[1]) if len(outs) > 1 else self._new("unused")
        if len(outs) < 2:
            self.decls.append(f"static int64_t {positions}[{max(outs[0].value.size, 1)}];")
        src = source.c_name
        self.body.append(
            f"for (i = 0; i < {groups.shape[0]}; ++i) {{ long order[{n}]; "
            f"for (long g = 0; g < {n}; ++g) {{ long c = g; {source.ctype} w = {src}[{read.format(g='g')}]; "
            f"while (c > 0) {{ {source.ctype} u = {src}[{read.format(g='order[c - 1]')}]; if (!({before})) break; "
            f"order[c] = order[c - 1]; --c; }} order[c] = g; }} "
            f"for (long g = 0; g < {k}; ++g) {{ {values}[{write.format(g='g')}] = {src}[{read.format(g='order[g]')}]; "
            f"{positions}[{write.format(g='g')}] = order[g]; }} }}"
        )

    def _index_table_2d(self, groups: np.ndarray) -> str:
        """A format string ``...{g}...`` reading group position g of output i."""
        rows, size = groups.shape
        base = groups[:, :1]
        steps = groups - base
        if rows and (steps == steps[0]).all() and (size < 2 or (np.diff(steps[0]) == steps[0][1] - steps[0][0]).all()):
            stride = int(steps[0][1] - steps[0][0]) if size > 1 else 0
            start = self._index_table(base[:, 0])
            return f"{start} + {{g}} * {stride}"
        return f"{self._table(groups)}[i * {size} + {{g}}]"

    def _matrix(self, tensor: _Tensor, transpose: bool) -> tuple[str, int, int, str]:
        """(name, rows, cols, index pattern) of a 2-D operand, read as row-major after ``transpose``."""
        rows, cols = tensor.value.shape
        if tensor.constant:
            value = tensor.value.T if transpose else tensor.value
            copy = _Tensor(tensor.name + "'", np.ascontiguousarray(value), True)
            return self._c(copy), value.shape[0], value.shape[1], "{r} * " + str(value.shape[1]) + " + {c}"
        if transpose:
            return tensor.c_name, cols, rows, "{c} * " + str(cols) + " + {r}"
        return tensor.c_name, rows, cols, "{r} * " + str(cols) + " + {c}"

    def _emit_product(self, a: _Tensor, b: _Tensor, trans_a: bool, trans_b: bool, out: _Tensor,
                      alpha: float = 1.0, bias: _Tensor | None = None, beta: float = 1.0) -> None:  # fmt: skip
        an, m, k, a_at = self._matrix(a, trans_a)
        bn, k2, n, b_at = self._matrix(b, trans_b)
        assert k == k2
        name = self._buffer(out)
        lines = [
            f"for (i = 0; i < {m}; ++i) {{ float *o = {name} + i * {n}; for (long j = 0; j < {n}; ++j) o[j] = 0.0f; "
            f"for (long p = 0; p < {k}; ++p) {{ const float x = {an}[{a_at.format(r='i', c='p')}]; "
            f"for (long j = 0; j < {n}; ++j) o[j] += x * {bn}[{b_at.format(r='p', c='j')}]; }} }}"
        ]
        if alpha != 1.0 or bias is not None:
            term = (
                f" + {_literal(beta, np.dtype(np.float32))} * {self._operand(bias, out.value.shape)}"
                if bias is not None
                else ""
            )
            lines.append(
                f"for (i = 0; i < {out.value.size}; ++i) "
                f"{name}[i] = {_literal(alpha, np.dtype(np.float32))} * {name}[i]{term};"
            )
        self.body.extend(lines)

    def _emit_gemm(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        a, b = ins[0], ins[1]
        bias = ins[2] if len(ins) > 2 else None
        assert a is not None and b is not None
        if a.value.dtype != np.float32:
            raise ValueError(f"{self.where}: Gemm on {a.value.dtype} is not handled")
        self._emit_product(a, b, bool(attrs.get("transA", 0)), bool(attrs.get("transB", 0)), out,
                           float(attrs.get("alpha", 1.0)), bias, float(attrs.get("beta", 1.0)))  # fmt: skip

    def _emit_matmul(self, op: str, attrs: dict[str, Any], ins: list[_Tensor | None], out: _Tensor) -> None:
        a, b = ins[0], ins[1]
        assert a is not None and b is not None
        if a.value.ndim != 2 or b.value.ndim != 2 or a.value.dtype != np.float32:
            raise ValueError(
                f"{self.where}: MatMul of shapes {a.value.shape} and {b.value.shape} is not handled (2-D only)"
            )
        self._emit_product(a, b, False, False, out)

    # -------------------------------------------------------------- branches
    #: operators that only re-shape a one-element tensor (a row's flag stays the same flag through them)
    _ALIASES = frozenset({"Reshape", "Unsqueeze", "Squeeze", "Identity", "Expand", "Flatten", "Cast"})

    def _flag(self, name: str, producers: dict[str, Any]) -> tuple[str, bool] | None:
        """``(root, polarity)`` of a computed one-element bool tensor: the tensor it re-shapes (or
        negates, polarity False) back to the first that is not a re-shape or ``Not``; None where
        ``name`` is not such a flag."""
        polarity = True
        while True:
            tensor = self.tensors.get(name)
            if tensor is None or tensor.constant or tensor.value.size != 1 or tensor.value.dtype != np.bool_:
                return None
            node = producers.get(name)
            if node is None or (node.op_type not in self._ALIASES and node.op_type != "Not"):
                return name, polarity
            source = self.tensors.get(node.input[0])
            if source is None or source.constant or source.value.size != 1 or source.value.dtype != np.bool_:
                return name, polarity
            polarity ^= node.op_type == "Not"
            name = node.input[0]

    def _gate_branches(self, graph_outputs: set[str]) -> int:
        """Put the work that only one side of a row's flag reads inside ``if`` on that flag.

        A row's decision often computes something it uses only on one side of a flag of that row:
        the switch filter's greedy backup input, read by ``Where(intervene, greedy, u*)`` and by
        its trust check ``And(untrusted, intervene)`` (``safety.tracing.only_rows``). A node is
        *gated* by a flag (one computed bool of the row, up to re-shapes and ``Not``) when every
        reader of its outputs is gated by the same flag, or is a ``Where`` on that flag reading it
        on the flag's side, or an ``And`` with the flag. Where the flag is off no reader looks at a
        gated node's value (``c ? a : b`` evaluates one side; ``a && 0`` is 0), so its statements
        run only where the flag is on. They move into ``if`` blocks right before their first
        ungated reader, keeping their order; their inputs are computed earlier, and every buffer is
        written once, so the move changes no value. Returns the number of gated nodes."""
        producers = {out: node for node, _, _ in self._emitted for out in node.output}
        order = {id(node): k for k, (node, _, _) in enumerate(self._emitted)}
        readers: dict[str, list[tuple[Any, int]]] = {}
        for node, _, _ in self._emitted:
            for slot, name in enumerate(node.input):
                readers.setdefault(name, []).append((node, slot))
        # a flag gates only what it cannot depend on (its root comes first: an And of two flags gates
        # the later one by the earlier, never each by the other), and only while the root itself is
        # computed unconditionally; a root found gated is barred and the gates are worked out again
        barred: set[str] = set()
        while True:
            gate = self._gates(producers, readers, order, graph_outputs, barred)
            roots = {root for root, _ in gate.values() if id(producers.get(root)) in gate}
            if not roots:
                break
            barred |= roots
        if not gate:
            return 0
        body: list[str] = []
        pending: dict[tuple[str, bool], list[str]] = {}
        for node, start, end in self._emitted:
            lines = self.body[start:end]
            if id(node) in gate:
                pending.setdefault(gate[id(node)], []).extend(lines)
                continue
            needed = {gate[id(producers[name])] for name in node.input if id(producers.get(name)) in gate}
            for flag in [f for f in pending if f in needed]:
                root, polarity = flag
                test = f"{self.tensors[root].c_name}[0]" if polarity else f"!{self.tensors[root].c_name}[0]"
                body.append(f"if ({test}) {{")
                body.extend("  " + line for line in pending.pop(flag))
                body.append("}")
            body.extend(lines)
        if pending:  # every gated node has an ungated reader, so nothing is left
            raise AssertionError("gated statements without a reader")
        self.body = body
        return len(gate)

    def _gates(
        self,
        producers: dict[str, Any],
        readers: dict[str, list[tuple[Any, int]]],
        order: dict[int, int],
        graph_outputs: set[str],
        barred: set[str],
    ) -> dict[int, tuple[str, bool]]:
        """``id(node) -> (flag root, polarity)`` of every gated node (see :meth:`_gate_branches`)."""
        gate: dict[int, tuple[str, bool]] = {}
        for node, _, _ in reversed(self._emitted):
            if any(out in graph_outputs for out in node.output):
                continue
            flags: set[tuple[str, bool] | None] = set()
            for out in node.output:
                for reader, slot in readers.get(out, []):
                    flag: tuple[str, bool] | None = None
                    if id(reader) in gate:
                        flag = gate[id(reader)]
                    elif reader.op_type == "Where" and slot in (1, 2):
                        found = self._flag(reader.input[0], producers)
                        flag = None if found is None else (found[0], found[1] == (slot == 1))
                    elif reader.op_type == "And" and len(reader.input) == 2:
                        flag = self._flag(reader.input[1 - slot], producers)
                    root_at = -1 if flag is None else order.get(id(producers.get(flag[0])), -1)
                    if flag is not None and (flag[0] in barred or root_at >= order[id(node)]):
                        flag = None
                    flags.add(flag)
            if len(flags) == 1 and None not in flags:
                gate[id(node)] = flags.pop()  # type: ignore[assignment]
        return gate

    # -------------------------------------------------------------- the file
    def source(self, prefix: str) -> str:
        rows = []
        params = [f"const {t.ctype} *{t.c_name}" for t in self.inputs]
        params += [f"{t.ctype} *out_{k}" for k, t in enumerate(self.outputs)]
        copies = []
        for k, t in enumerate(self.outputs):
            src = self._c(t) if t.constant else t.c_name
            copies.append(f"memcpy(out_{k}, {src}, {max(t.value.size, 1)} * sizeof({t.ctype}));")
        rows.append(_PRELUDE)
        rows.extend(self.decls)
        rows.append(f"static int {prefix}_row({', '.join(params)}) {{\n  long i;\n  (void)i;")
        rows.extend("  " + line for line in self.body)
        rows.extend("  " + line for line in copies)
        rows.append("  return 0;\n}")
        # the batch entry point: row by row, scalar boolean outputs ORed over the rows
        per_row_in = [t.value.size for t in self.inputs]
        batch_params = ["long n"] + [f"const {t.ctype} *{t.c_name}" for t in self.inputs]
        batch_params += [f"{t.ctype} *out_{k}" for k, t in enumerate(self.outputs)]
        loop_args = [f"{t.c_name} + r * {size}" for t, size in zip(self.inputs, per_row_in)]
        scalar_init, scalar_or = [], []
        for k, t in enumerate(self.outputs):
            if t.value.ndim == 0:
                scalar_init.append(f"*out_{k} = 0; {t.ctype} s_{k} = 0;")
                loop_args.append(f"&s_{k}")
                scalar_or.append(f"*out_{k} = *out_{k} || s_{k};")
            else:
                loop_args.append(f"out_{k} + r * {t.value.size}")
        rows.append(f"int {prefix}({', '.join(batch_params)}) {{")
        rows.extend("  " + line for line in scalar_init)
        rows.append(f"  for (long r = 0; r < n; ++r) {{\n    int status = {prefix}_row({', '.join(loop_args)});")
        rows.append("    if (status) return status;")
        rows.extend("    " + line for line in scalar_or)
        rows.append("  }\n  return 0;\n}")
        return "\n".join(rows) + "\n"


def _check_row_shapes(emitter: _Emitter, where: str) -> None:
    """Every input and output is one row per state (leading batch axis of 1), or a scalar boolean
    output (a flag over the batch), so that deciding row by row is the batch's decision."""
    for t in emitter.inputs:
        if t.value.ndim == 0 or t.value.shape[0] != 1:
            raise ValueError(f"{where}: input {t.name} has no leading batch axis")
    for t in emitter.outputs:
        if t.value.ndim == 0 and t.value.dtype != np.bool_:
            raise ValueError(f"{where}: output {t.name} is a scalar that is not a flag")
        if t.value.ndim and t.value.shape[0] != 1:
            raise ValueError(f"{where}: output {t.name} has no leading batch axis")


def _emitter_for(path: str | os.PathLike) -> _Emitter:
    try:
        import onnx  # lazy: only reading the graph needs onnx
    except ImportError:
        raise ValueError("the native engine reads the graph with the onnx package: pip install onnx") from None
    where = os.fspath(path)
    if not os.path.isfile(where):
        raise ValueError(f"{where}: no such file (an exported filter is one .onnx file)")
    try:
        model = onnx.load(where)
    except Exception as error:  # onnx raises protobuf's own errors for a file it cannot parse
        raise ValueError(f"{where}: not a readable ONNX model ({type(error).__name__}: {error})") from None
    emitter = _Emitter(model, where)
    emitter.metadata = {prop.key: prop.value for prop in model.metadata_props}
    _check_row_shapes(emitter, where)
    return emitter


def c_source(path: str | os.PathLike, function: str = "reach_filter") -> str:
    """The exported filter at ``path`` as one C file defining
    ``int function(long n, const float *state, const float *time_to_go, const float *u_nominal,
    <outputs>...)``: ``n`` states row-major, the outputs in the graph's order (``control``,
    ``value``, ``gradient``, then the flags as ``unsigned char``). It returns 0, or 2 where a
    computed index fell outside its tensor (the decision must not be used). Not reentrant: its
    buffers are static, so call it from one thread at a time."""
    if not function.isidentifier():
        raise ValueError(f"function must be a C identifier, got {function!r}")
    return _c_file(_emitter_for(path), path, function)


def _c_file(emitter: _Emitter, path: str | os.PathLike, function: str) -> str:
    """The C file of an emitted graph (:func:`c_source`)."""
    header = [
        f"/* {Path(os.fspath(path)).name}, compiled by reach_runtime.native: one decision per row. */",
        "/* inputs: " + ", ".join(f"{t.name} {t.ctype}[{t.value.size}]" for t in emitter.inputs) + " per row */",
        "/* outputs: " + ", ".join(f"{t.name} {t.ctype}[{max(t.value.size, 1)}]" for t in emitter.outputs) + " */",
    ]
    return "\n".join(header) + "\n" + emitter.source(function) + _checked_entry(emitter, function)


#: the checked entry point's return codes (``<function>_checked``), as the C file defines them
STATUS = {
    "REACH_OK": 0,
    "REACH_BAD_INPUT": 1,
    "REACH_INDEX_OUT_OF_RANGE": 2,
    "REACH_TIME_OUT_OF_RANGE": 3,
    "REACH_UNTRUSTED": 4,
}


def _checked_entry(emitter: _Emitter, function: str) -> str:
    """For an exported reach filter: ``<function>_checked``, the runtime's input checks in C (a
    state, time or nominal input that is NaN or inf; a time-to-go outside the range the value
    function covers) before the decision, and the batch refused where the graph flags it
    ``untrusted``; so a controller that calls it fails closed as ``reach_runtime.Filter`` does.
    Nothing for a graph without the filter's metadata and interface."""
    meta = emitter.metadata
    names_in = [t.name for t in emitter.inputs]
    names_out = [t.name for t in emitter.outputs]
    if (
        "reach.time_range" not in meta
        or names_in != ["state", "time_to_go", "u_nominal"]
        or "untrusted" not in names_out
    ):
        return ""
    low, high = (float(v) for v in json.loads(meta["reach.time_range"]))
    tol = 1e-6 * max(1.0, abs(high))  # as the Python runtime's _TIME_TOLERANCE
    n_state, n_control = emitter.inputs[0].value.shape[1], emitter.inputs[2].value.shape[1]
    untrusted = names_out.index("untrusted")
    params = ", ".join(f"{t.ctype} *out_{k}" for k, t in enumerate(emitter.outputs))
    args = ", ".join(f"out_{k}" for k in range(len(emitter.outputs)))
    codes = "\n".join(f"#define {name} {code}" for name, code in STATUS.items())
    return f"""
/* The runtime's checks, in C: returns REACH_OK, or a code saying why the batch must not be used. */
{codes}
#define REACH_STATE_DIM {n_state}
#define REACH_CONTROL_DIM {n_control}
static const double reach_time_range[2] = {{{low!r}, {high!r}}};
int {function}_checked(long n, const float *state, const float *time_to_go, const float *u_nominal, {params}) {{
  for (long r = 0; r < n * {n_state}; ++r) if (!isfinite(state[r])) return REACH_BAD_INPUT;
  for (long r = 0; r < n * {n_control}; ++r) if (!isfinite(u_nominal[r])) return REACH_BAD_INPUT;
  for (long r = 0; r < n; ++r) {{
    if (!isfinite(time_to_go[r])) return REACH_BAD_INPUT;
    if (time_to_go[r] < {low!r} - {tol!r} || time_to_go[r] > {high!r} + {tol!r}) return REACH_TIME_OUT_OF_RANGE;
  }}
  int status = {function}(n, state, time_to_go, u_nominal, {args});
  if (status) return status;
  return *out_{untrusted} ? REACH_UNTRUSTED : REACH_OK;
}}
"""


def _compiler() -> str:
    chosen = os.environ.get("CC")
    if chosen:
        if not shutil.which(chosen):
            raise ValueError(f"$CC is {chosen!r}, which is not a program on PATH")
        return chosen
    for name in ("cc", "gcc", "clang"):
        if shutil.which(name):
            return name
    raise ValueError("the native engine needs a C compiler (cc, gcc or clang on PATH, or $CC)")


#: flags of the build: optimised and vectorised for this machine (-O3 -march=native; no FP traps and
#: no errno, so that loops with comparisons and square roots vectorise), with IEEE values kept: no
#: -ffast-math, so NaN and inf propagate and the graph's own non-finite checks still see them
CFLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-fPIC", "-shared")


def compile_filter(path: str | os.PathLike, cache: str | os.PathLike | None = None) -> Path:
    """Build the filter at ``path`` into a shared library (cached under ``cache``, default
    ``$XDG_CACHE_HOME/reach_runtime`` or ``~/.cache/reach_runtime``, by the hash of its source and
    flags) and return the library's path. ``ValueError`` if the graph or the compiler refuses."""
    return _build(c_source(path), path, cache)


def _build(source: str, path: str | os.PathLike, cache: str | os.PathLike | None) -> Path:
    """The shared library of ``source`` (the C file of the filter at ``path``), built or found in the cache."""
    compiler = _compiler()
    key = hashlib.sha256((source + " ".join(CFLAGS) + compiler).encode()).hexdigest()[:24]
    folder = (
        Path(cache)
        if cache is not None
        else Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "reach_runtime"
    )
    folder.mkdir(parents=True, exist_ok=True)
    library = folder / f"filter-{key}.so"
    if library.exists():
        return library
    with tempfile.TemporaryDirectory(dir=folder) as work:
        c_file = Path(work) / "filter.c"
        c_file.write_text(source)
        built = Path(work) / "filter.so"
        result = subprocess.run(
            [compiler, *CFLAGS, "-o", str(built), str(c_file), "-lm"], capture_output=True, text=True
        )
        if result.returncode != 0:
            raise ValueError(
                f"{os.fspath(path)}: the C compiler refused the generated source: {result.stderr.strip()[-400:]}"
            )
        os.replace(built, library)  # atomic: a concurrent build of the same key writes the same bytes
    return library


class NativeGraph:
    """The compiled decision, called like ``session.run``: ``graph.run(feeds) -> list of outputs``."""

    def __init__(self, path: str | os.PathLike, cache: str | os.PathLike | None = None) -> None:
        emitter = _emitter_for(path)  # read and emitted once: the library is built from the same emitter
        self._library_path = _build(_c_file(emitter, path, "reach_filter"), path, cache)
        self._lib = ctypes.CDLL(str(self._library_path))
        self._fn = self._lib.reach_filter
        self._fn.restype = ctypes.c_int
        self._inputs = [(t.name, t.value.dtype, t.value.shape[1:]) for t in emitter.inputs]
        self._outputs = [(t.name, t.value.dtype, t.value.shape) for t in emitter.outputs]
        self._lock = threading.Lock()  # the generated code's buffers are static: one call at a time
        self._slots: dict[int, tuple[list[np.ndarray], list[np.ndarray], list[Any]]] = {}
        self.input_names = [name for name, _, _ in self._inputs]
        self.output_names = [name for name, _, _ in self._outputs]
        # the C file's checked entry (a reach filter's graph only): one state, checks and all, in C
        checked = getattr(self._lib, "reach_filter_checked", None)
        self._row = None if checked is None else (checked, *self._allocate(1))

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """The outputs for ``feeds`` (arrays with a leading batch axis), in the graph's order.

        The C function reads and writes buffers kept per batch size (their addresses are resolved
        once: at batch 1 that lookup would cost more than the decision); the inputs are copied in
        and the outputs copied out, so no call's results share memory with another's."""
        arrays = [feeds[name] for name in self.input_names]
        n = int(np.shape(arrays[0])[0]) if np.ndim(arrays[0]) else 0
        with self._lock:  # the generated code's buffers are static, and so are these
            slots = self._slots.get(n)
            if slots is None:
                slots = self._slots[n] = self._allocate(n)
                if len(self._slots) > 8:
                    self._slots.pop(next(iter(self._slots)))
            ins, outs, args = slots
            for slot, array, (name, _, _) in zip(ins, arrays, self._inputs):
                if np.shape(array) != slot.shape:
                    raise ValueError(f"{name} must have shape {slot.shape}, got {np.shape(array)}")
                np.copyto(slot, array, casting="same_kind")
            status = self._fn(*args)
            results = [o.copy() for o in outs]
        if status != 0:
            raise ValueError("the compiled filter met an index outside its tensor; the decision is not trusted")
        return results

    def checked_row(self, state: np.ndarray, time_to_go: float, u_nominal: np.ndarray) -> tuple[int, list[np.ndarray]]:
        """One state through the C file's checked entry (``reach_filter_checked``): the status
        (:data:`STATUS`; nonzero: the decision must not be used, and the outputs are then
        meaningless) and copies of the outputs, each ``(1, ...)`` or a flag. ``state`` and
        ``u_nominal`` are float32 rows of the graph's widths (not checked here: the caller's fast
        path has). The per-call cost of :meth:`run` less its dictionary, shape checks and NumPy
        checks of finiteness, which the C entry makes."""
        if self._row is None:
            raise ValueError("this graph has no checked entry (it is not an exported reach filter)")
        function, ins, outs, args = self._row
        with self._lock:
            ins[0][0] = state
            ins[1][0] = time_to_go
            ins[2][0] = u_nominal
            status = function(*args)
            return status, [o.copy() for o in outs]

    def bound(self, feeds: dict[str, np.ndarray]) -> Any:
        """A call of the C function alone on ``feeds``, without arguments (to time the compiled
        code apart from the copies and checks around it). Its outputs are discarded."""
        arrays = [np.asarray(feeds[name]) for name in self.input_names]
        ins, outs, args = self._allocate(int(arrays[0].shape[0]))
        for slot, array in zip(ins, arrays):
            np.copyto(slot, array, casting="same_kind")
        function = self._fn

        def call(_buffers: tuple = (ins, outs)) -> int:  # held: the arguments point into these buffers
            return function(*args)

        return call

    def _allocate(self, n: int) -> tuple[list[np.ndarray], list[np.ndarray], list[Any]]:
        ins = [np.zeros((n, *row), dtype) for _, dtype, row in self._inputs]
        outs = [np.zeros((n, *shape[1:]) if shape else (), dtype) for _, dtype, shape in self._outputs]
        args = [ctypes.c_long(n), *(ctypes.c_void_p(a.ctypes.data) for a in (*ins, *outs))]
        return ins, outs, args

    @property
    def library(self) -> Path:
        """The shared library this graph runs."""
        return self._library_path
