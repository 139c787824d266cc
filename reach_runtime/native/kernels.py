"""Each computed node as C statements over static buffers, one function per operator family.

Elementwise operators become one loop over the output, reading each operand broadcast through an
index (:meth:`~reach_runtime.native.buffers.CodeBuffers.operand`); data movement (slices,
transposes, broadcasts, gathers with fixed indices) becomes a copy through the positions the same
NumPy operation gives on its input's positions; gathers with computed indices check each index
(the C function returns 2 for one outside its tensor); reductions, ``ArgMax``/``ArgMin`` and
``TopK`` loop over groups; ``Gemm`` and ``MatMul`` over rows. :data:`KERNELS` names the function
of each family (:func:`family`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from reach_runtime.native.buffers import CodeBuffers, literal
from reach_runtime.native.folding import Tensor, axes_of, evaluate
from reach_runtime.native.operators import BINARY, DOUBLE, FLOAT_ONLY, MOVES, REDUCTIONS, UNARY

__all__ = ["KERNELS", "emit_topk", "family"]

Attributes = dict[str, Any]
Inputs = list[Tensor | None]


def family(op: str) -> str:
    """The operator family of a computed node (a key of :data:`KERNELS`)."""
    if op in UNARY or op in BINARY or op in ("Where", "Cast", "Clip"):
        return "elementwise"
    if op in ("Gather", "GatherND"):
        return "gather"
    if op in MOVES:
        return "move"
    families = {"Concat": "concat", "Gemm": "gemm", "MatMul": "matmul", "ArgMax": "argmax", "ArgMin": "argmax"}
    return families.get(op, "gather_elements" if op == "GatherElements" else "reduce")


def emit_elementwise(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """One loop over the output: the operator's C expression of its operands, each read broadcast."""
    shape = out.value.shape
    name = code.buffer(out)
    if op == "Where":
        c, a, b = (code.operand(t, shape) for t in ins)  # type: ignore[arg-type]
        expr = f"{c} ? {a} : {b}"
    elif op == "Cast":
        a = code.operand(ins[0], shape)  # type: ignore[arg-type]
        expr = f"({a} != 0)" if out.value.dtype == np.bool_ else f"({out.ctype})({a})"
    elif op == "Clip":
        expr = code.operand(ins[0], shape)  # type: ignore[arg-type]
        if len(ins) > 1 and ins[1] is not None:
            expr = f"RMAX({expr}, {code.operand(ins[1], shape)})"
        if len(ins) > 2 and ins[2] is not None:
            expr = f"RMIN({expr}, {code.operand(ins[2], shape)})"
    elif op in ("Max", "Min") and len(ins) != 2:
        expr = code.operand(ins[0], shape)  # type: ignore[arg-type]
        for t in ins[1:]:
            expr = f"R{op.upper()}({expr}, {code.operand(t, shape)})"  # type: ignore[arg-type]
    elif op in UNARY:
        template = UNARY[op]
        if op in FLOAT_ONLY and out.value.dtype == np.float64:
            template = DOUBLE[op]
        elif op in FLOAT_ONLY and out.value.dtype != np.float32:
            raise ValueError(f"{code.where}: {op} on {out.value.dtype} is not handled")
        expr = template.format(a=code.operand(ins[0], shape))  # type: ignore[arg-type]
    else:
        template = BINARY[op]
        if op == "Pow" and out.value.dtype != np.float32:
            if out.value.dtype != np.float64:
                raise ValueError(f"{code.where}: Pow on {out.value.dtype} is not handled")
            template = DOUBLE["Pow"]
        expr = template.format(a=code.operand(ins[0], shape), b=code.operand(ins[1], shape))  # type: ignore[arg-type]
    code.body.append(f"for (i = 0; i < {out.value.size}; ++i) {name}[i] = ({out.ctype})({expr});")


def emit_move(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """Data movement: the output's positions of the input, by the same op on the input's positions."""
    source = ins[0]
    assert source is not None and not source.constant
    if any(t is not None and not t.constant for t in ins[1:]):
        raise ValueError(f"{code.where}: {op} with a computed shape or index is not handled")
    positions = np.arange(source.value.size, dtype=np.int64).reshape(source.value.shape)
    with np.errstate(all="ignore"):
        moved = evaluate(op, attrs, [positions, *[t.value if t is not None else None for t in ins[1:]]])
    name = code.buffer(out)
    code.body.append(f"for (i = 0; i < {out.value.size}; ++i) {name}[i] = {source.c_name}[{code.index_table(moved)}];")


def emit_gather(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """``Gather``/``GatherND``: a move where the indices are constant; otherwise each computed index
    is checked against its axis (the C function returns 2 for one outside it)."""
    data, indices = ins[0], ins[1]
    assert data is not None and indices is not None
    if indices.constant:
        if data.constant:
            return
        emit_move(code, op, attrs, ins, out)
        return
    if op == "GatherND" and attrs.get("batch_dims", 0):
        raise ValueError(f"{code.where}: GatherND with batch_dims is not handled")
    src = code.c(data)
    name = code.buffer(out)
    dims = data.value.shape
    idx = indices.c_name
    if op == "Gather":
        axis = attrs.get("axis", 0) % data.value.ndim
        outer = int(np.prod(dims[:axis], dtype=np.int64))
        inner = int(np.prod(dims[axis + 1 :], dtype=np.int64))
        count = indices.value.size
        code.body.append(
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
    code.body.append(
        f"for (long q = 0; q < {count}; ++q) {{ long off = 0; {offset} "
        f"for (long r = 0; r < {piece}; ++r) {name}[q * {piece} + r] = {src}[off + r]; }}"
    )


def emit_concat(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """One copy per input, into the output positions it takes along ``axis``."""
    name = code.buffer(out)
    sizes = [t.value.size for t in ins]  # type: ignore[union-attr]
    starts = np.cumsum([0, *sizes])
    tagged = [starts[k] + np.arange(t.value.size, dtype=np.int64).reshape(t.value.shape) for k, t in enumerate(ins)]  # type: ignore[union-attr]
    placed = np.concatenate(tagged, axis=attrs["axis"]).reshape(-1)
    for k, t in enumerate(ins):
        assert t is not None
        where = np.nonzero((placed >= starts[k]) & (placed < starts[k + 1]))[0]
        source = placed[where] - starts[k]
        code.body.append(
            f"for (i = 0; i < {where.size}; ++i) "
            f"{name}[{code.index_table(where)}] = {code.c(t)}[{code.index_table(source)}];"
        )


def emit_reduce(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """``ReduceMin``/``ReduceMax``/``ReduceSum``: one accumulator per output over its group of inputs."""
    source = ins[0]
    assert source is not None
    if len(ins) > 1 and ins[1] is not None and not ins[1].constant:
        raise ValueError(f"{code.where}: {op} over computed axes is not handled")
    axes = ins[1].value if len(ins) > 1 and ins[1] is not None else attrs.get("axes")
    shape = source.value.shape
    if axes is None or np.asarray(axes).size == 0:
        if attrs.get("noop_with_empty_axes", 0):
            emit_move(code, "Identity", {}, [source], out)
            return
        reduced = tuple(range(len(shape)))
    else:
        reduced = tuple(sorted(axes_of(axes, len(shape))))
    kept = tuple(d for d in range(len(shape)) if d not in reduced)
    groups = np.transpose(np.arange(source.value.size).reshape(shape), kept + reduced).reshape(out.value.size, -1)
    name = code.buffer(out)
    table = code.index_table_2d(groups)
    combine = REDUCTIONS[op]
    code.body.append(
        f"for (i = 0; i < {out.value.size}; ++i) {{ {out.ctype} m = {source.c_name}[{table.format(g=0)}]; "
        f"for (long g = 1; g < {groups.shape[1]}; ++g) "
        f"m = {combine.format(m='m', v=source.c_name + '[' + table.format(g='g') + ']')}; "
        f"{name}[i] = m; }}"
    )


def emit_argmax(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """``ArgMax``/``ArgMin`` along ``axis``: the first extreme of each group, a NaN counting as both."""
    source = ins[0]
    assert source is not None
    if attrs.get("select_last_index", 0):
        raise ValueError(f"{code.where}: {op} with select_last_index is not handled")
    axis = attrs.get("axis", 0) % source.value.ndim
    positions = np.moveaxis(np.arange(source.value.size).reshape(source.value.shape), axis, -1)
    groups = positions.reshape(-1, source.value.shape[axis])
    name = code.buffer(out)
    table = code.index_table_2d(groups)
    # the first largest (smallest), a NaN counting as both, as NumPy and torch pick it
    better = "v > m" if op == "ArgMax" else "v < m"
    code.body.append(
        f"for (i = 0; i < {out.value.size}; ++i) {{ long best = 0; "
        f"{source.ctype} m = {source.c_name}[{table.format(g=0)}]; "
        f"for (long g = 1; g < {groups.shape[1]}; ++g) {{ "
        f"{source.ctype} v = {source.c_name}[{table.format(g='g')}]; "
        f"if (m == m && ({better} || v != v)) {{ m = v; best = g; }} }} {name}[i] = best; }}"
    )


def emit_gather_elements(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """``out[..., j, ...] = data[..., index[..., j, ...], ...]`` along ``axis``: the position with
    the axis coordinate set to 0 (strided) plus the index times the axis stride."""
    data, indices = ins[0], ins[1]
    assert data is not None and indices is not None
    if indices.constant:
        emit_move(code, op, attrs, ins, out)
        return
    axis = attrs.get("axis", 0) % data.value.ndim
    dims = data.value.shape
    stride = int(np.prod(dims[axis + 1 :], dtype=np.int64))
    origin = np.ravel_multi_index(
        tuple(np.zeros_like(c) if k == axis else c for k, c in enumerate(np.indices(out.value.shape))), dims
    )
    name = code.buffer(out)
    code.body.append(
        f"for (i = 0; i < {out.value.size}; ++i) {{ long j = (long){indices.c_name}[i]; "
        f"if (j < 0) j += {dims[axis]}; if (j < 0 || j >= {dims[axis]}) return 2; "
        f"{name}[i] = {code.c(data)}[{code.index_table(origin)} + j * {stride}]; }}"
    )


def emit_topk(code: CodeBuffers, attrs: Attributes, ins: Inputs, outs: list[Tensor]) -> None:
    """The k smallest (largest) along ``axis``, sorted, ties in index order: a stable insertion
    sort of each group's positions (groups are a handful of breakpoints in exported filters)."""
    source, k_input = ins[0], ins[1]
    assert source is not None and k_input is not None
    if not k_input.constant:
        raise ValueError(f"{code.where}: TopK with a computed k is not handled")
    if not attrs.get("sorted", 1):
        raise ValueError(f"{code.where}: TopK unsorted is not handled")
    axis = attrs.get("axis", -1) % source.value.ndim
    n = source.value.shape[axis]
    k = int(np.asarray(k_input.value).reshape(-1)[0])
    before = "w < u" if not attrs.get("largest", 1) else "w > u"
    groups = np.moveaxis(np.arange(source.value.size).reshape(source.value.shape), axis, -1).reshape(-1, n)
    placed = np.moveaxis(np.arange(outs[0].value.size).reshape(outs[0].value.shape), axis, -1).reshape(-1, k)
    read, write = code.index_table_2d(groups), code.index_table_2d(placed)
    values = code.buffer(outs[0])
    positions = code.buffer(outs[1]) if len(outs) > 1 else code.new_name("unused")
    if len(outs) < 2:
        code.decls.append(f"static int64_t {positions}[{max(outs[0].value.size, 1)}];")
    src = source.c_name
    code.body.append(
        f"for (i = 0; i < {groups.shape[0]}; ++i) {{ long order[{n}]; "
        f"for (long g = 0; g < {n}; ++g) {{ long c = g; {source.ctype} w = {src}[{read.format(g='g')}]; "
        f"while (c > 0) {{ {source.ctype} u = {src}[{read.format(g='order[c - 1]')}]; if (!({before})) break; "
        f"order[c] = order[c - 1]; --c; }} order[c] = g; }} "
        f"for (long g = 0; g < {k}; ++g) {{ {values}[{write.format(g='g')}] = {src}[{read.format(g='order[g]')}]; "
        f"{positions}[{write.format(g='g')}] = order[g]; }} }}"
    )


def matrix(code: CodeBuffers, tensor: Tensor, transpose: bool) -> tuple[str, int, int, str]:
    """(name, rows, cols, index pattern) of a 2-D operand, read as row-major after ``transpose``."""
    rows, cols = tensor.value.shape
    if tensor.constant:
        value = tensor.value.T if transpose else tensor.value
        copy = Tensor(tensor.name + "'", np.ascontiguousarray(value), True)
        return code.c(copy), value.shape[0], value.shape[1], "{r} * " + str(value.shape[1]) + " + {c}"
    if transpose:
        return tensor.c_name, cols, rows, "{c} * " + str(cols) + " + {r}"
    return tensor.c_name, rows, cols, "{r} * " + str(cols) + " + {c}"


def emit_product(
    code: CodeBuffers,
    a: Tensor,
    b: Tensor,
    out: Tensor,
    transpose: tuple[bool, bool] = (False, False),
    alpha: float = 1.0,
    bias: Tensor | None = None,
    beta: float = 1.0,
) -> None:
    """``out = alpha * op(a) @ op(b) + beta * bias``, ``op`` transposing where ``transpose`` says:
    rows of ``out`` accumulated over ``p`` in a loop that vectorises over its columns."""
    an, m, k, a_at = matrix(code, a, transpose[0])
    bn, k2, n, b_at = matrix(code, b, transpose[1])
    assert k == k2
    name = code.buffer(out)
    lines = [
        f"for (i = 0; i < {m}; ++i) {{ float *o = {name} + i * {n}; for (long j = 0; j < {n}; ++j) o[j] = 0.0f; "
        f"for (long p = 0; p < {k}; ++p) {{ const float x = {an}[{a_at.format(r='i', c='p')}]; "
        f"for (long j = 0; j < {n}; ++j) o[j] += x * {bn}[{b_at.format(r='p', c='j')}]; }} }}"
    ]
    if alpha != 1.0 or bias is not None:
        term = (
            f" + {literal(beta, np.dtype(np.float32))} * {code.operand(bias, out.value.shape)}"
            if bias is not None
            else ""
        )
        lines.append(
            f"for (i = 0; i < {out.value.size}; ++i) "
            f"{name}[i] = {literal(alpha, np.dtype(np.float32))} * {name}[i]{term};"
        )
    code.body.extend(lines)


def emit_gemm(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """``Gemm`` in float32 (:func:`emit_product`)."""
    a, b = ins[0], ins[1]
    bias = ins[2] if len(ins) > 2 else None
    assert a is not None and b is not None
    if a.value.dtype != np.float32:
        raise ValueError(f"{code.where}: Gemm on {a.value.dtype} is not handled")
    transpose = (bool(attrs.get("transA", 0)), bool(attrs.get("transB", 0)))
    alpha, beta = float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0))
    emit_product(code, a, b, out, transpose, alpha, bias, beta)


def emit_matmul(code: CodeBuffers, op: str, attrs: Attributes, ins: Inputs, out: Tensor) -> None:
    """``MatMul`` of two 2-D float32 operands (:func:`emit_product`)."""
    a, b = ins[0], ins[1]
    assert a is not None and b is not None
    if a.value.ndim != 2 or b.value.ndim != 2 or a.value.dtype != np.float32:
        raise ValueError(
            f"{code.where}: MatMul of shapes {a.value.shape} and {b.value.shape} is not handled (2-D only)"
        )
    emit_product(code, a, b, out)


#: the function that emits each family of single-output operators (``TopK``: :func:`emit_topk`)
KERNELS: dict[str, Callable[[CodeBuffers, str, Attributes, Inputs, Tensor], None]] = {
    "elementwise": emit_elementwise,
    "move": emit_move,
    "gather": emit_gather,
    "concat": emit_concat,
    "reduce": emit_reduce,
    "argmax": emit_argmax,
    "gather_elements": emit_gather_elements,
    "gemm": emit_gemm,
    "matmul": emit_matmul,
}
