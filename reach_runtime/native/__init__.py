"""An exported filter compiled to straight-line C: one decision at control-loop rate, no graph runtime.

ONNX Runtime spends about a microsecond dispatching each node of a graph, and an exported filter's
decision is several hundred nodes (the network, its input gradient, the failure margin's autograd,
the backup input's candidates). At batch 1 that dispatch, not the arithmetic, is the latency. This
package turns the graph into one C function instead:

- every tensor's shape is fixed by a batch of one state, so shapes, ``Shape``/``Reshape``
  arithmetic and every node that depends only on constants are evaluated here, once, with NumPy;
- each remaining node becomes a loop over static buffers; data movement (slices, transposes,
  broadcasts, gathers with fixed indices) becomes copies through index tables computed by running
  the same NumPy operation on the positions of its input;
- the weights become ``static const`` arrays;
- work that only one side of a row's flag reads runs inside ``if`` on that flag (the switch's
  greedy backup input only where it intervenes: :mod:`reach_runtime.native.branches`).

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
refused, naming it. A cached library is loaded only where its size and SHA-256 match those its
build recorded; a truncated, overwritten or foreign one is built again, never loaded.

The modules, in the order a graph passes through them: :mod:`~reach_runtime.native.operators`
(the operator tables), :mod:`~reach_runtime.native.acceptance` (what graphs are accepted),
:mod:`~reach_runtime.native.folding` (constant folding at batch 1),
:mod:`~reach_runtime.native.buffers` and :mod:`~reach_runtime.native.kernels` (the C of each
node), :mod:`~reach_runtime.native.branches` (work gated by a row's flag),
:mod:`~reach_runtime.native.emission` (the C file), :mod:`~reach_runtime.native.build` (the
compiler and its checked cache) and :mod:`~reach_runtime.native.library` (the loaded library).
"""

from reach_runtime.native.build import CFLAGS, compile_filter
from reach_runtime.native.emission import STATUS, c_source
from reach_runtime.native.library import NativeGraph
from reach_runtime.native.operators import SUPPORTED_OPS

__all__ = ["CFLAGS", "STATUS", "SUPPORTED_OPS", "NativeGraph", "c_source", "compile_filter"]
