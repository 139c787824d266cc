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

A file is trusted as a checkpoint is: it carries the SHA-256 of its graph, weights and metadata
(:mod:`reach_runtime.digest`), and one whose digest is missing or does not match is refused, naming
it. ``filter.metadata.source_verdict`` says whether its source passed the trust bar when exported.

This package imports only the standard library, NumPy and ONNX Runtime; its native engine
(``Filter.load(path, engine="native")``, :mod:`reach_runtime.native`: the graph compiled to C, a
fraction of the latency at batch 1, checked against ONNX Runtime on sampled states before it
decides) also reads the graph with the ``onnx`` package and needs a C compiler. Copy its folder
next to your controller and ``pip install numpy onnxruntime onnx``.
``reach_runtime.native.c_source(path)`` is the C file alone, for a controller without Python.
"""

from reach_runtime.filter import Filter, FilterInfo
from reach_runtime.metadata import FilterMetadata

__all__ = ["Filter", "FilterInfo", "FilterMetadata"]
