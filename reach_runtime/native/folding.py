"""Constant folding: each operator's NumPy semantics, run once on the graph at a batch of one state.

Every tensor's shape is fixed by a batch of one state, so shapes, ``Shape``/``Reshape`` arithmetic
and every node that depends only on constants are evaluated here, once, with NumPy
(:func:`fold`); only the nodes that read a computed tensor are left for C. The same semantics
(:func:`evaluate`) run on the positions of a tensor give the index tables of data movement
(:mod:`reach_runtime.native.kernels`), and they are the reference the C code is checked against.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from reach_runtime.native.operators import BINARY, CTYPES, DTYPES, REDUCTIONS, UNARY

__all__ = ["Tensor", "attributes", "axes_of", "evaluate", "fold"]


@dataclass
class Tensor:
    """One tensor of the graph at batch 1, and the C name it has once emitted."""

    name: str
    value: np.ndarray  # its value at batch 1 for a constant; zeros of its shape and dtype otherwise
    constant: bool
    c_name: str = ""

    @property
    def ctype(self) -> str:
        return CTYPES[self.value.dtype.name]


def attributes(node: Any) -> dict[str, Any]:
    """A node's attributes as Python values."""
    import onnx  # lazy: reading the graph is the only use of onnx, and running needs none

    return {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}


def axes_of(values: Any, rank: int) -> tuple[int, ...]:
    """Axes given as an array (negative ones counting from the end) as non-negative ints."""
    return tuple(int(a) % rank for a in np.asarray(values).reshape(-1))


def evaluate(op: str, attrs: dict[str, Any], xs: list[np.ndarray | None]) -> np.ndarray:
    """One node's output, in NumPy (the reference the C code is generated from and checked against)."""
    a = xs[0]
    if op in UNARY:
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
    if op in BINARY:
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
        return a.astype(DTYPES[attrs["to"]])
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
        axes = axes_of(xs[1], a.ndim) if len(xs) > 1 and xs[1] is not None else None
        return np.squeeze(a, axis=axes)
    if op == "Unsqueeze":
        rank = a.ndim + np.asarray(xs[1]).size
        out = a
        for axis in sorted(axes_of(xs[1], rank)):
            out = np.expand_dims(out, axis)
        return out
    if op == "Reshape":
        shape = [int(s) for s in xs[1]]
        if not attrs.get("allowzero", 0):
            shape = [a.shape[i] if s == 0 else s for i, s in enumerate(shape)]
        return a.reshape(shape)
    if op == "Slice":
        starts, ends = np.asarray(xs[1]), np.asarray(xs[2])
        axes = axes_of(xs[3], a.ndim) if len(xs) > 3 and xs[3] is not None else tuple(range(starts.size))
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
    if op in REDUCTIONS:
        axes = xs[1] if len(xs) > 1 and xs[1] is not None else attrs.get("axes")
        if axes is None or np.asarray(axes).size == 0:
            if attrs.get("noop_with_empty_axes", 0):
                return a.copy()
            axis = None
        else:
            axis = axes_of(axes, a.ndim)
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


def fold(
    node: Any, tensors: dict[str, Tensor], where: str
) -> tuple[dict[str, Any], list[Tensor | None], list[Tensor]] | None:
    """Evaluate ``node`` at batch 1 and enter its outputs in ``tensors``.

    None where the node is folded (a ``Constant``, a ``Shape``, or a node that reads only
    constants: its outputs' values are known here). Otherwise ``(attributes, inputs, outputs)``
    of a node left for C, its outputs entered as computed tensors (zeros of their shape and dtype).
    ``ValueError`` naming the node where the NumPy semantics refuse its shapes or types."""
    op = node.op_type
    attrs = attributes(node)
    if op == "Constant":
        from onnx import numpy_helper  # lazy: reading the graph is the only use of onnx

        value = next(a for a in node.attribute if a.name == "value")
        tensors[node.output[0]] = Tensor(node.output[0], numpy_helper.to_array(value.t), True)
        return None
    ins = [tensors[name] if name else None for name in node.input]
    values = [t.value if t is not None else None for t in ins]
    try:
        with np.errstate(all="ignore"):  # folding may divide by zero exactly as the graph would
            out_value = evaluate(op, attrs, values)
    except Exception as error:  # a shape or type the NumPy semantics refuse names the node
        raise ValueError(f"{where}: node {node.name or op} ({op}) cannot be evaluated at batch 1: {error}") from None
    values_out = out_value if isinstance(out_value, tuple) else (out_value,)
    if len([name for name in node.output if name]) > len(values_out):
        raise ValueError(f"{where}: node {node.name or op} ({op}) has more outputs than it computes")
    outs = [Tensor(name, np.asarray(v), True) for name, v in zip(node.output, values_out)]
    for t in outs:
        tensors[t.name] = t
    dynamic = [t for t in ins if t is not None and not t.constant]
    if op == "Shape" or not dynamic:
        return None  # folded: its value is known here
    for t in outs:
        t.constant = False
        t.value = np.zeros(t.value.shape, t.value.dtype)
    return attrs, ins, outs
