"""The checks an exported filter passes when it is loaded, before its first decision.

- **The interface** (:func:`check_interface`): the graph's inputs and outputs are the filter's, each
  with a free batch dimension shared by all of them, and widths that are the metadata's. The runtime
  checks a call's shapes against these, so a wrong width is a ``ValueError`` naming it, never ONNX
  Runtime's ``InvalidArgument``.
- **The graph follows its metadata** (:func:`check_follows_metadata`), on states sampled from the
  domain and a margin beyond it (:func:`sampled_feeds`): ``outside_domain`` is set exactly where
  a state leaves the domain of ``reach.domain`` (states with a heading, ``reach.wrapped_dims``,
  beyond its bounds are wrapped first and not judged); and
  for the switch, whose rule reads only ``V``, the decision is ``V`` against the threshold of
  ``reach.settings`` oriented by ``reach.problem``. These are values the graph bakes in; the digest
  (:mod:`reach_runtime.digest`) already ties the metadata to the graph, and this checks that the
  exporter wrote the values it traced.
- **The native engine** (:func:`check_native`) decides as ONNX Runtime does on the same states.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from reach_runtime.metadata import FilterMetadata

__all__ = ["CHECK_STATES", "INPUTS", "OUTPUTS", "check_follows_metadata", "check_interface", "check_native"]

#: the graph's inputs, in order, with their rank
INPUTS = (("state", 2), ("time_to_go", 1), ("u_nominal", 2))

#: the graph's outputs (``untrusted`` is one flag for the batch, the others one row per state)
OUTPUTS = ("control", "value", "gradient", "intervened", "infeasible", "outside_domain", "untrusted")

#: states sampled for the load checks (one batch)
CHECK_STATES = 256


def _shape(arg: Any) -> list[Any]:
    shape = arg.shape
    return list(shape) if isinstance(shape, (list, tuple)) else []


def check_interface(session: Any, meta: FilterMetadata, where: str) -> None:
    """Refuse a graph whose inputs or outputs are not the filter's, whose batch dimension is fixed
    (an export traced with the batch tied to another size), or whose widths differ from the
    metadata's ``state_dim`` and ``control_dim``; each naming the file and what differs."""
    inputs = session.get_inputs()
    names = [i.name for i in inputs]
    if names != [name for name, _ in INPUTS]:
        raise ValueError(f"{where}: the graph's inputs are {names}, not {[name for name, _ in INPUTS]}")
    outputs = {o.name: o for o in session.get_outputs()}
    if not set(OUTPUTS) <= set(outputs):
        raise ValueError(f"{where}: the graph lacks outputs {sorted(set(OUTPUTS) - set(outputs))}")
    widths = {"state": meta.state_dim, "u_nominal": meta.control_dim}
    batch = set()
    for arg, (name, rank) in zip(inputs, INPUTS):
        shape = _shape(arg)
        if arg.type != "tensor(float)" or len(shape) != rank:
            raise ValueError(
                f"{where}: the graph's input {name} is {arg.type} of shape {shape}, not float32 of rank {rank}"
            )
        if isinstance(shape[0], int):
            raise ValueError(
                f"{where}: the graph fixes {name}'s batch dimension to {shape[0]}; it must be free (export it again)"
            )
        batch.add(shape[0])
        if name in widths and shape[1] != widths[name]:
            raise ValueError(f"{where}: the graph's {name} has width {shape[1]}, its metadata says {widths[name]}")
    for name in OUTPUTS[:-1]:
        shape = _shape(outputs[name])
        if not shape or isinstance(shape[0], int):
            raise ValueError(f"{where}: the graph's output {name} has shape {shape}, without a free batch dimension")
        batch.add(shape[0])
    if len(batch) != 1:
        raise ValueError(f"{where}: the graph's inputs and outputs do not share one batch dimension ({sorted(batch)})")


def sampled_feeds(meta: FilterMetadata, count: int = CHECK_STATES) -> dict[str, np.ndarray]:
    """``count`` states drawn uniformly from the domain and 5 % beyond it on each side (where the
    filter must intervene), times-to-go over the range, nominal inputs over the input set; float32."""
    rng = np.random.default_rng(0)
    low, high = np.array(meta.domain, dtype=np.float64).T
    span = high - low
    x = rng.uniform(low - 0.05 * span, high + 0.05 * span, size=(count, meta.state_dim))
    t = rng.uniform(*meta.time_range, size=count)
    box = meta.control_set.get("box")
    if box is not None:
        u = rng.uniform(
            np.array(box["low"], dtype=np.float64),
            np.array(box["high"], dtype=np.float64),
            size=(count, meta.control_dim),
        )
    else:
        ball = meta.control_set["ball"]
        direction = rng.normal(size=(count, meta.control_dim))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        u = np.array(ball["center"]) + float(ball["radius"]) * rng.uniform(0, 1, (count, 1)) * direction
    return {"state": x.astype(np.float32), "time_to_go": t.astype(np.float32), "u_nominal": u.astype(np.float32)}


def check_follows_metadata(
    feeds: dict[str, np.ndarray], out: dict[str, np.ndarray], meta: FilterMetadata, where: str
) -> None:
    """Refuse a graph whose ``outside_domain`` is not the metadata's domain, or (the switch) whose
    decisions are not ``V`` against the metadata's threshold on the side its problem kind trusts.
    Rows within float32 rounding of the threshold are not judged; an ``untrusted`` batch (the
    graph met a non-finite value: every call would be refused) is not judged either."""
    if bool(np.asarray(out["untrusted"]).any()):
        return
    x = feeds["state"]
    bounds = np.array(meta.domain, dtype=np.float32)
    leaves = (x < bounds[:, 0]) | (x > bounds[:, 1])
    known = ~leaves[:, list(meta.wrapped_dims)].any(-1)  # a heading beyond its bounds is wrapped first: not judged here
    outside = leaves.any(-1)
    flagged = np.asarray(out["outside_domain"], dtype=bool)
    if not np.array_equal(flagged[known], outside[known]):
        wrong = int((flagged != outside)[known].sum())
        raise ValueError(
            f"{where}: the graph's domain is not its metadata's (reach.domain): outside_domain differs on {wrong} of "
            f"{len(x)} sampled states; export it again"
        )
    if meta.kind != "switch":
        return
    value = np.asarray(out["value"], dtype=np.float32)
    oriented = -value if meta.reaches else value
    threshold = np.float32(meta.threshold)
    keep = oriented > threshold
    if meta.settings.get("outside_domain", "backup") != "extrapolate":
        keep &= ~outside
    judged = known & (np.abs(oriented - threshold) > 1e-6 * max(1.0, abs(float(threshold))))
    if meta.reaches:
        judged &= feeds["time_to_go"] > 0
    wrong = int(((np.asarray(out["intervened"], dtype=bool) == keep) & judged).sum())
    if wrong:
        raise ValueError(
            f"{where}: the graph does not decide by its metadata's threshold {meta.threshold:g} (reach.settings) on "
            f"the side of a {meta.problem} problem (reach.problem): {wrong} of {int(judged.sum())} sampled states "
            "differ; export it again"
        )


def check_native(feeds: dict[str, np.ndarray], expected: dict[str, np.ndarray], native: Any, where: str) -> None:
    """Refuse a compiled graph that does not decide as ONNX Runtime did (``expected``) on ``feeds``.

    One batch, so a graph that mixes rows, or any miscompilation, is caught before the first
    decision. Values and gradients must agree to float32 rounding (matrix sums run in another
    order), the flags exactly, and the decision on all but 1 % of the states (a state within
    rounding of the threshold may go either way)."""
    got = dict(zip(native.output_names, native.run(feeds)))
    trusted = not bool(expected["untrusted"]) and not bool(got["untrusted"])
    problems = []
    if bool(expected["untrusted"]) != bool(got["untrusted"]):
        problems.append("its untrusted flag")
    if trusted:
        if not np.allclose(got["value"], expected["value"], rtol=1e-4, atol=1e-4):
            problems.append("values")
        if not np.allclose(got["gradient"], expected["gradient"], rtol=1e-3, atol=1e-3):
            problems.append("gradients")
        for flag in ("outside_domain", "infeasible"):
            if not np.array_equal(got[flag], expected[flag]):
                problems.append(flag)
        if (got["intervened"] != expected["intervened"]).mean() > 0.01:
            problems.append("decisions")
    if problems:
        raise ValueError(
            f"{where}: the compiled filter disagrees with ONNX Runtime on {', '.join(problems)} over "
            f"{len(feeds['state'])} sampled states; it is not used (load it with engine='onnxruntime')"
        )
