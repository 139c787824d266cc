"""The C file's storage: static buffers, constant arrays and index tables, and how a statement
reads them.

:class:`CodeBuffers` holds the declarations and the statements emitted so far. A constant becomes
a ``static const`` array on first use (once per distinct content); a computed tensor a static
buffer; data movement reads through an index on the output position ``i``: ``i`` itself, a
constant, strided arithmetic (:func:`strided`) or a static table.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from reach_runtime.native.folding import Tensor

__all__ = ["CodeBuffers", "array_literal", "literal", "strided"]


def strided(index: np.ndarray) -> str | None:
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


def literal(v: Any, dtype: np.dtype) -> str:
    """One value as a C literal of ``dtype``: the shortest decimal that reads back to the same float."""
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


def array_literal(values: np.ndarray) -> str:
    """An array's values, flattened, as a C initialiser ``{...}``."""
    flat = values.reshape(-1)
    return "{" + ",".join(literal(v, values.dtype) for v in flat) + "}"


class CodeBuffers:
    """The declarations (``decls``) and statements (``body``) of the C file being written, and the
    names of its buffers, constants and index tables. ``where`` (the graph's file) names errors."""

    def __init__(self, where: str) -> None:
        self.where = where
        self.decls: list[str] = []
        self.body: list[str] = []
        self._count = 0
        self._constants: dict[tuple[str, str], str] = {}

    def new_name(self, prefix: str) -> str:
        """A fresh C name: ``prefix`` and a number counted over the whole file."""
        self._count += 1
        return f"{prefix}{self._count}"

    def c(self, tensor: Tensor) -> str:
        """The C name of a tensor, emitting a constant's array on first use (once per distinct
        content: a lookahead's backup steps fold the same weights many times over)."""
        if not tensor.c_name:
            values = np.ascontiguousarray(tensor.value).reshape(-1)
            key = (values.dtype.str, hashlib.sha256(values.tobytes()).hexdigest())
            if key in self._constants:
                tensor.c_name = self._constants[key]
                return tensor.c_name
            tensor.c_name = self._constants[key] = self.new_name("k")
            self.decls.append(
                f"static const {tensor.ctype} {tensor.c_name}[{max(values.size, 1)}] = "
                f"{array_literal(values if values.size else np.zeros(1, values.dtype))};"
            )
        return tensor.c_name

    def buffer(self, tensor: Tensor) -> str:
        """A new static buffer for a computed tensor; its C name."""
        tensor.c_name = self.new_name("t")
        self.decls.append(f"static {tensor.ctype} {tensor.c_name}[{max(tensor.value.size, 1)}];")
        return tensor.c_name

    def index_table(self, index: np.ndarray) -> str:
        """``name[i]`` for a static index table, or ``i`` / a constant where the table is one."""
        flat = np.asarray(index, dtype=np.int64).reshape(-1)
        if flat.size and np.array_equal(flat, np.arange(flat.size)):
            return "i"
        if flat.size and (flat == flat[0]).all():
            return str(int(flat[0]))
        arithmetic = strided(np.asarray(index, dtype=np.int64))
        if arithmetic is not None:
            return arithmetic
        return f"{self.table(flat)}[i]"

    def table(self, values: np.ndarray) -> str:
        """A static index table (int32 where the positions allow), shared by equal tables."""
        flat = np.asarray(values, dtype=np.int64).reshape(-1)
        small = flat.size == 0 or (flat.min(initial=0) >= -(2**31) and flat.max(initial=0) < 2**31)
        return self.c(Tensor("table", flat.astype(np.int32 if small else np.int64), True))

    def index_table_2d(self, groups: np.ndarray) -> str:
        """A format string ``...{g}...`` reading group position g of output i."""
        rows, size = groups.shape
        base = groups[:, :1]
        steps = groups - base
        if rows and (steps == steps[0]).all() and (size < 2 or (np.diff(steps[0]) == steps[0][1] - steps[0][0]).all()):
            stride = int(steps[0][1] - steps[0][0]) if size > 1 else 0
            start = self.index_table(base[:, 0])
            return f"{start} + {{g}} * {stride}"
        return f"{self.table(groups)}[i * {size} + {{g}}]"

    def operand(self, tensor: Tensor, shape: tuple[int, ...]) -> str:
        """``name[index]`` reading ``tensor`` broadcast to ``shape`` at output position ``i``."""
        positions = np.arange(tensor.value.size).reshape(tensor.value.shape)
        return f"{self.c(tensor)}[{self.index_table(np.broadcast_to(positions, shape))}]"
