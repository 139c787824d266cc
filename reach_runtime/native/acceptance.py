"""What graphs the native engine accepts, checked before any C is written.

An exported filter is one readable ONNX file whose digest matches (:func:`load_model`), whose inputs have element types
the compiler handles and whose operators are all in
:data:`~reach_runtime.native.operators.SUPPORTED_OPS` (:func:`check_graph`), and whose every input
and output is one row per state or a scalar flag (:func:`check_row_shapes`), so that deciding row
by row is the batch's decision. Each refusal is one ``ValueError`` naming the file and what it
holds that the compiler does not handle.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from reach_runtime.digest import read_model
from reach_runtime.native.folding import Tensor
from reach_runtime.native.operators import DTYPES, SUPPORTED_OPS

__all__ = ["check_graph", "check_row_shapes", "load_model"]


def load_model(path: str | os.PathLike) -> tuple[Any, str]:
    """The ONNX model at ``path``, and the path as a string (errors name it). The file is read once;
    one that carries ``reach.*`` metadata (an exported filter) is refused unless its digest matches
    (:mod:`reach_runtime.digest`), as ``Filter.load`` refuses it; a graph without them (a test's,
    a user's) is compiled as it is."""
    try:
        import onnx  # lazy: only reading the graph needs onnx
    except ImportError:
        raise ValueError("the native engine reads the graph with the onnx package: pip install onnx") from None
    where = os.fspath(path)
    if not os.path.isfile(where):
        raise ValueError(f"{where}: no such file (an exported filter is one .onnx file)")
    read = read_model(where)
    if any(key.startswith("reach.") for key in read.metadata):
        read.verify()  # an exported filter: compiled only where its digest matches
    try:
        model = onnx.load_from_string(read.data)
    except Exception as error:  # onnx raises protobuf's own errors for a file it cannot parse
        raise ValueError(f"{where}: not a readable ONNX model ({type(error).__name__}: {error})") from None
    return model, where


def check_graph(graph: Any, where: str) -> None:
    """Every input (other than an initializer) has an element type the compiler handles, and every
    operator is one it reads."""
    initializers = {init.name for init in graph.initializer}
    for value in graph.input:
        if value.name not in initializers and DTYPES.get(value.type.tensor_type.elem_type) is None:
            raise ValueError(f"{where}: input {value.name} has an element type the native compiler does not handle")
    unsupported = sorted({n.op_type for n in graph.node} - SUPPORTED_OPS)
    if unsupported:
        raise ValueError(f"{where}: operators the native compiler does not handle: {', '.join(unsupported)}")


def check_row_shapes(inputs: list[Tensor], outputs: list[Tensor], where: str) -> None:
    """Every input and output is one row per state (leading batch axis of 1), or a scalar boolean
    output (a flag over the batch), so that deciding row by row is the batch's decision."""
    for t in inputs:
        if t.value.ndim == 0 or t.value.shape[0] != 1:
            raise ValueError(f"{where}: input {t.name} has no leading batch axis")
    for t in outputs:
        if t.value.ndim == 0 and t.value.dtype != np.bool_:
            raise ValueError(f"{where}: output {t.name} is a scalar that is not a flag")
        if t.value.ndim and t.value.shape[0] != 1:
            raise ValueError(f"{where}: output {t.name} has no leading batch axis")
