"""The operators the native compiler reads, as tables: their element types (NumPy dtypes and C
types), the C expression of each elementwise operator, the data movements and the reductions.

:data:`SUPPORTED_OPS` is every operator exported filters are made of; a graph with another is
refused (:mod:`reach_runtime.native.acceptance`).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "BINARY",
    "CTYPES",
    "DOUBLE",
    "DTYPES",
    "FLOAT_ONLY",
    "MOVES",
    "REDUCTIONS",
    "SUPPORTED_OPS",
    "UNARY",
]

#: ONNX element types the compiler handles, as NumPy dtypes and C types
DTYPES = {
    1: np.dtype(np.float32), 6: np.dtype(np.int32), 7: np.dtype(np.int64), 9: np.dtype(np.bool_),
    11: np.dtype(np.float64),
}  # fmt: skip
CTYPES = {"float32": "float", "int32": "int32_t", "int64": "int64_t", "bool": "unsigned char", "float64": "double"}

#: elementwise operators: the C expression of their operands a, b (c: Where's condition)
UNARY = {
    "Abs": "RABS({a})", "Neg": "(-{a})", "Sin": "rsin_q({a}, 0.0f)", "Cos": "rsin_q({a}, 1.0f)", "Sqrt": "sqrtf({a})",
    "Round": "rintf({a})", "Sign": "(({a}) != ({a}) ? ({a}) : (({a}) > 0) - (({a}) < 0))", "Not": "(!{a})",
    "Identity": "{a}", "Exp": "expf({a})", "Log": "logf({a})", "Tanh": "tanhf({a})", "Erf": "erff({a})",
    "Floor": "floorf({a})", "Ceil": "ceilf({a})", "Relu": "RMAX({a}, 0)", "Reciprocal": "(1 / ({a}))",
    "Sigmoid": "(1 / (1 + expf(-({a}))))",
}  # fmt: skip
BINARY = {
    "Add": "{a} + {b}", "Sub": "{a} - {b}", "Mul": "{a} * {b}", "Div": "{a} / {b}",
    "Equal": "{a} == {b}", "Greater": "{a} > {b}", "Less": "{a} < {b}", "GreaterOrEqual": "{a} >= {b}",
    "LessOrEqual": "{a} <= {b}", "And": "{a} && {b}", "Or": "{a} || {b}",
    "Max": "RMAX({a}, {b})", "Min": "RMIN({a}, {b})", "Pow": "powf({a}, {b})",
}  # fmt: skip
#: unary operators whose C functions are float32 ones
FLOAT_ONLY = {"Sin", "Cos", "Sqrt", "Round", "Exp", "Log", "Tanh", "Erf", "Floor", "Ceil", "Sigmoid"}
#: the same in float64 (the smooth filter's projection is solved in float64): the C library's own
DOUBLE = {
    "Sin": "sin({a})", "Cos": "cos({a})", "Sqrt": "sqrt({a})", "Round": "rint({a})", "Exp": "exp({a})",
    "Log": "log({a})", "Tanh": "tanh({a})", "Erf": "erf({a})", "Floor": "floor({a})", "Ceil": "ceil({a})",
    "Sigmoid": "(1 / (1 + exp(-({a}))))", "Pow": "pow({a}, {b})",
}  # fmt: skip
#: data movement: copies through index tables (:mod:`reach_runtime.native.kernels`)
MOVES = {"Slice", "Transpose", "Expand", "Tile", "Reshape", "Squeeze", "Unsqueeze", "Identity", "Gather", "GatherND"}
#: reductions: how an accumulator m takes in the next operand v
REDUCTIONS = {"ReduceMin": "RMIN({m}, {v})", "ReduceMax": "RMAX({m}, {v})", "ReduceSum": "{m} + {v}"}

#: every operator the compiler reads (what exported filters are made of)
SUPPORTED_OPS = frozenset(
    set(UNARY) | set(BINARY) | MOVES | set(REDUCTIONS)
    | {"Where", "Cast", "Clip", "Concat", "Gemm", "MatMul", "ArgMax", "ArgMin", "Shape", "Constant", "Range"}
    | {"GatherElements", "TopK"}
)  # fmt: skip
