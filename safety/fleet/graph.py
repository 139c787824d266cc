"""Conflicts of a fleet: the connected groups of cars that must decide together, batched.

The cars of every state in a batch are nodes ``b * N + k`` of one graph; the pairs a filter finds
active are its edges. Two cars joined by a chain of active pairs must choose their inputs together
(a car answering one pair moves in the other), while groups with no active pair between them decide
independently. :func:`conflicts` labels the groups by vectorised label propagation over all states
at once (each node takes the least label among its neighbours, then the label of its label, until
nothing changes: a handful of sweeps, each a scatter over the edges) and says which groups hold a
pair that triggers a decision.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["Conflicts", "components", "conflicts"]


def components(num_nodes: int, src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """``(num_nodes,)``: each node's label, the least node of its connected component (undirected
    edges ``src[k] - dst[k]``)."""
    label = torch.arange(num_nodes, device=src.device)
    if src.numel() == 0:
        return label
    while True:
        low = torch.minimum(label[src], label[dst])
        new = label.scatter_reduce(0, src, low, reduce="amin").scatter_reduce(0, dst, low, reduce="amin")
        new = new[new]  # pointer jumping: a label's own label is in the same component and no larger
        if torch.equal(new, label):
            return label
        label = new


@dataclass(frozen=True)
class Conflicts:
    """The groups of cars joined by active pairs, and which of them must decide.

    Attributes:
        node_label: ``(B * N,)`` each car's group (the least node of it).
        edge_label: ``(E,)`` each active pair's group.
        in_conflict: ``(E,)`` bool: the pair's group holds a triggering pair (a *conflict*).
        car_in_conflict: ``(B, N)`` bool: the car belongs to a conflict.
        edges_in_group: ``(E,)`` how many active pairs the pair's group has.
        count: ``(B,)`` conflicts per state.
    """

    node_label: torch.Tensor
    edge_label: torch.Tensor
    in_conflict: torch.Tensor
    car_in_conflict: torch.Tensor
    edges_in_group: torch.Tensor
    count: torch.Tensor


def conflicts(
    batch: int, n: int, edges: tuple[torch.Tensor, torch.Tensor, torch.Tensor], trigger: torch.Tensor
) -> Conflicts:
    """The conflicts of ``batch`` states of ``n`` cars whose active pairs are ``edges = (b, i, j)``
    (flat ``(E,)`` tensors), a group being a conflict where some pair of it has ``trigger``."""
    b, i, j = edges
    device = b.device
    u, v = b * n + i, b * n + j
    label = components(batch * n, u, v)
    edge_label = label[u]
    hot = torch.zeros(batch * n, dtype=torch.bool, device=device)
    hot[edge_label[trigger]] = True
    in_conflict = hot[edge_label]
    has_edge = torch.zeros(batch * n, dtype=torch.bool, device=device)
    has_edge[u] = True
    has_edge[v] = True
    car_in_conflict = (hot[label] & has_edge).reshape(batch, n)
    per_group = torch.zeros(batch * n, dtype=torch.long, device=device).scatter_add(0, edge_label, torch.ones_like(u))
    return Conflicts(
        label, edge_label, in_conflict, car_in_conflict, per_group[edge_label], hot.reshape(batch, n).sum(1)
    )
