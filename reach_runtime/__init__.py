"""Run an exported reach safety filter with NumPy and ONNX Runtime only: no torch, no reach.

``reach export SOURCE --out f.onnx`` (or :func:`safety.filters.export.export_filter`) writes the filter's
whole decision as one ONNX graph; on the robot::

    from reach_runtime import Filter

    shield = Filter.load("f.onnx")
    u, info = shield(x, u_nominal)          # one state (n,) and input (m,), or a batch (B, n), (B, m)
    u, info = shield(x, u_nominal, t=0.8)   # a time-to-go (required where it counts down)

It fails closed as the torch filter does: a wrong shape, NaN or inf in a state or nominal input, or
a time-to-go outside the range the value function covers raises ``ValueError`` before the graph
runs; a non-finite value, gradient or optimal input met in the graph raises too (its ``untrusted``
output); a state outside the domain keeps no nominal input (``info.outside_domain``).
``info.intervened`` says where the nominal input was overridden.

This package imports only the standard library, NumPy and ONNX Runtime: copy its folder next to
your controller and ``pip install numpy onnxruntime``. ``Filter.load(path, engine="native")``
compiles the graph to C instead (:mod:`reach_runtime.native`: a fraction of the latency at batch 1;
it needs a C compiler, and the ``onnx`` package to read the graph), checked against ONNX Runtime
on sampled states before it decides; ``reach_runtime.native.c_source(path)`` is the C file alone,
for a controller without Python.
"""

from reach_runtime.filter import Filter, FilterInfo, FilterMetadata

__all__ = ["Filter", "FilterInfo", "FilterMetadata"]
