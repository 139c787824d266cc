"""Work that only one side of a row's flag reads runs inside ``if`` on that flag.

A row's decision often computes something it uses only on one side of a flag of that row: the
switch filter's greedy backup input, read by ``Where(intervene, greedy, u*)`` and by its trust
check ``And(untrusted, intervene)`` (``safety.tracing.only_rows``). :func:`gate_branches` moves
the statements of such work into ``if`` blocks, so that the switch computes its greedy input only
where it intervenes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from reach_runtime.native.folding import Tensor

__all__ = ["ALIASES", "gate_branches"]

#: operators that only re-shape a one-element tensor (a row's flag stays the same flag through them)
ALIASES = frozenset({"Reshape", "Unsqueeze", "Squeeze", "Identity", "Expand", "Flatten", "Cast"})

#: a flag: the tensor it comes from (its root) and whether the flag is that tensor (True) or its negation
Flag = tuple[str, bool]


def gate_branches(
    emitted: list[tuple[Any, int, int]], tensors: dict[str, Tensor], body: list[str], graph_outputs: set[str]
) -> tuple[list[str], int]:
    """Put the work that only one side of a row's flag reads inside ``if`` on that flag.

    ``emitted`` holds ``(node, first line, end)`` of each emitted node's statements in ``body``.
    A node is *gated* by a flag (one computed bool of the row, up to re-shapes and ``Not``) when
    every reader of its outputs is gated by the same flag, or is a ``Where`` on that flag reading
    it on the flag's side, or an ``And`` with the flag. Where the flag is off no reader looks at a
    gated node's value (``c ? a : b`` evaluates one side; ``a && 0`` is 0), so its statements run
    only where the flag is on. They move into ``if`` blocks right before their first ungated
    reader, keeping their order; their inputs are computed earlier, and every buffer is written
    once, so the move changes no value. Returns the new body and the number of gated nodes (the
    body unchanged where there are none)."""
    graph = _Readers(emitted, tensors)
    # a flag gates only what it cannot depend on (its root comes first: an And of two flags gates
    # the later one by the earlier, never each by the other), and only while the root itself is
    # computed unconditionally; a root found gated is barred and the gates are worked out again
    barred: set[str] = set()
    while True:
        gate = graph.gates(graph_outputs, barred)
        roots = {root for root, _ in gate.values() if id(graph.producers.get(root)) in gate}
        if not roots:
            break
        barred |= roots
    if not gate:
        return body, 0
    gated: list[str] = []
    pending: dict[Flag, list[str]] = {}
    for node, start, end in emitted:
        lines = body[start:end]
        if id(node) in gate:
            pending.setdefault(gate[id(node)], []).extend(lines)
            continue
        needed = {gate[id(graph.producers[name])] for name in node.input if id(graph.producers.get(name)) in gate}
        for flag in [f for f in pending if f in needed]:
            root, polarity = flag
            test = f"{tensors[root].c_name}[0]" if polarity else f"!{tensors[root].c_name}[0]"
            gated.append(f"if ({test}) {{")
            gated.extend("  " + line for line in pending.pop(flag))
            gated.append("}")
        gated.extend(lines)
    if pending:  # every gated node has an ungated reader, so nothing is left
        raise AssertionError("gated statements without a reader")
    return gated, len(gate)


class _Readers:
    """The emitted nodes' data flow: who produces each tensor, who reads it (and in which input
    slot), and each node's position in the order of emission."""

    def __init__(self, emitted: list[tuple[Any, int, int]], tensors: dict[str, Tensor]) -> None:
        self.emitted = emitted
        self.tensors = tensors
        self.producers = {out: node for node, _, _ in emitted for out in node.output}
        self.order = {id(node): k for k, (node, _, _) in enumerate(emitted)}
        self.readers: dict[str, list[tuple[Any, int]]] = {}
        for node, _, _ in emitted:
            for slot, name in enumerate(node.input):
                self.readers.setdefault(name, []).append((node, slot))

    def flag(self, name: str) -> Flag | None:
        """``(root, polarity)`` of a computed one-element bool tensor: the tensor it re-shapes (or
        negates, polarity False) back to the first that is not a re-shape or ``Not``; None where
        ``name`` is not such a flag."""
        polarity = True
        while True:
            tensor = self.tensors.get(name)
            if tensor is None or tensor.constant or tensor.value.size != 1 or tensor.value.dtype != np.bool_:
                return None
            node = self.producers.get(name)
            if node is None or (node.op_type not in ALIASES and node.op_type != "Not"):
                return name, polarity
            source = self.tensors.get(node.input[0])
            if source is None or source.constant or source.value.size != 1 or source.value.dtype != np.bool_:
                return name, polarity
            polarity ^= node.op_type == "Not"
            name = node.input[0]

    def gates(self, graph_outputs: set[str], barred: set[str]) -> dict[int, Flag]:
        """``id(node) -> (flag root, polarity)`` of every gated node (see :func:`gate_branches`)."""
        gate: dict[int, Flag] = {}
        for node, _, _ in reversed(self.emitted):
            if any(out in graph_outputs for out in node.output):
                continue
            flags: set[Flag | None] = set()
            for out in node.output:
                for reader, slot in self.readers.get(out, []):
                    flag: Flag | None = None
                    if id(reader) in gate:
                        flag = gate[id(reader)]
                    elif reader.op_type == "Where" and slot in (1, 2):
                        found = self.flag(reader.input[0])
                        flag = None if found is None else (found[0], found[1] == (slot == 1))
                    elif reader.op_type == "And" and len(reader.input) == 2:
                        flag = self.flag(reader.input[1 - slot])
                    root_at = -1 if flag is None else self.order.get(id(self.producers.get(flag[0])), -1)
                    if flag is not None and (flag[0] in barred or root_at >= self.order[id(node)]):
                        flag = None
                    flags.add(flag)
            if len(flags) == 1 and None not in flags:
                gate[id(node)] = flags.pop()  # type: ignore[assignment]
        return gate
