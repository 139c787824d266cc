"""The graph as one C file: straight-line C over static buffers, one decision per row.

:class:`Emitter` reads the graph, folds what depends only on constants
(:mod:`reach_runtime.native.folding`), writes each remaining node as C statements
(:mod:`reach_runtime.native.kernels`) and moves the work one side of a row's flag reads inside
``if`` on it (:mod:`reach_runtime.native.branches`). :func:`c_source` is the C file of an exported
filter: the per-row function, the batch entry point, and for a reach filter the checked entry
point, whose return codes are :data:`STATUS`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from reach_runtime.native.acceptance import check_graph, check_row_shapes, load_model
from reach_runtime.native.branches import gate_branches
from reach_runtime.native.buffers import CodeBuffers
from reach_runtime.native.folding import Tensor, fold
from reach_runtime.native.kernels import KERNELS, emit_topk, family
from reach_runtime.native.operators import DTYPES

__all__ = ["PRELUDE", "STATUS", "Emitter", "c_file", "c_source", "emitter_for"]

#: the C file's first lines: the headers, and the helpers the operators' expressions use
PRELUDE = """\
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


class Emitter(CodeBuffers):
    """Turns the graph, folded at batch 1, into C statements over static buffers.

    ``inputs`` and ``outputs`` are the graph's, ``gated`` the number of nodes whose statements
    run only on one side of a row's flag, ``metadata`` the model's metadata properties."""

    def __init__(self, model: Any, where: str) -> None:
        from onnx import numpy_helper  # lazy: reading the graph is the only use of onnx (running needs none)

        super().__init__(where)
        self.metadata: dict[str, str] = {prop.key: prop.value for prop in model.metadata_props}
        graph = model.graph
        check_graph(graph, where)
        self.tensors: dict[str, Tensor] = {}
        for init in graph.initializer:
            self.tensors[init.name] = Tensor(init.name, numpy_helper.to_array(init), True)
        self.inputs: list[Tensor] = []
        for value in graph.input:
            if value.name in self.tensors:
                continue
            dtype = DTYPES[value.type.tensor_type.elem_type]
            dims = [d.dim_value if d.HasField("dim_value") else 1 for d in value.type.tensor_type.shape.dim]
            tensor = Tensor(value.name, np.zeros(dims, dtype), False, f"in_{len(self.inputs)}")
            self.tensors[value.name] = tensor
            self.inputs.append(tensor)
        emitted: list[tuple[Any, int, int]] = []  # (node, first body line, end) of each emitted node
        for node in graph.node:
            start = len(self.body)
            self._node(node)
            if len(self.body) > start:
                emitted.append((node, start, len(self.body)))
        self.outputs = [self.tensors[o.name] for o in graph.output]
        self.body, self.gated = gate_branches(emitted, self.tensors, self.body, {o.name for o in graph.output})

    def _node(self, node: Any) -> None:
        """Fold ``node``, or write its statements where it reads a computed tensor."""
        computed = fold(node, self.tensors, self.where)
        if computed is None:
            return
        attrs, ins, outs = computed
        op = node.op_type
        if op == "TopK":
            emit_topk(self, attrs, ins, outs)
            return
        if op == "Range":
            raise ValueError(f"{self.where}: Range over computed bounds is not handled")
        KERNELS[family(op)](self, op, attrs, ins, outs[0])

    def source(self, prefix: str) -> str:
        """The C of the graph: ``static int <prefix>_row(...)`` deciding one row, and
        ``int <prefix>(long n, ...)`` deciding ``n`` rows, its scalar flags ORed over the rows."""
        rows = []
        params = [f"const {t.ctype} *{t.c_name}" for t in self.inputs]
        params += [f"{t.ctype} *out_{k}" for k, t in enumerate(self.outputs)]
        copies = []
        for k, t in enumerate(self.outputs):
            src = self.c(t) if t.constant else t.c_name
            copies.append(f"memcpy(out_{k}, {src}, {max(t.value.size, 1)} * sizeof({t.ctype}));")
        rows.append(PRELUDE)
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


def emitter_for(path: str | os.PathLike) -> Emitter:
    """The graph of the exported filter at ``path``, emitted; ``ValueError`` naming the file where
    the native engine does not accept it (:mod:`reach_runtime.native.acceptance`)."""
    model, where = load_model(path)
    emitter = Emitter(model, where)
    check_row_shapes(emitter.inputs, emitter.outputs, where)
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
    return c_file(emitter_for(path), path, function)


def c_file(emitter: Emitter, path: str | os.PathLike, function: str) -> str:
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


def _checked_entry(emitter: Emitter, function: str) -> str:
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
    tol = 1e-6 * max(1.0, abs(high))  # as the Python runtime's TIME_TOLERANCE
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
