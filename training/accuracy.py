"""Accuracy of a value function against a reference one (e.g. a grid ground truth).

Uses only the value-function interface (``value(x, t)``), so training does not depend on the grid
solver; the caller passes the reference and the states to compare on.
"""

from __future__ import annotations

from typing import Any

import torch


def compare(
    candidate: Any, reference_values: torch.Tensor, states: torch.Tensor, t: float, chunk: int = 65536
) -> dict[str, float]:
    """MSE of ``V`` and IoU of ``{V <= 0}`` between ``candidate`` and precomputed reference values."""
    values = torch.cat([candidate.value(s, t).detach().cpu() for s in states.split(chunk)])
    ref = reference_values.to(values.dtype)
    inside_c, inside_r = values <= 0, ref <= 0
    union = (inside_c | inside_r).sum().item()
    return {
        "mse": float((values - ref).square().mean()),
        "iou": float((inside_c & inside_r).sum().item() / union) if union else 1.0,
    }


class ReferenceEvaluator:
    """Callable ``evaluator(value_function) -> metrics`` over a volume and one 2D slice of a grid.

    ``reference`` is a grid solution (anything with ``grid.points()`` and ``value(x, t)``); the
    volume is all its nodes, the slice the nodes of dimension ``slice_dim`` nearest ``slice_value``
    (default: the system's :meth:`~reach.systems.base.ControlAffineSystem.reference_slice`, x3 = 1.5863
    for Air3D), or, when ``slice_states`` and ``slice_values`` are given, those (e.g. the toolbox's slice).
    """

    def __init__(
        self,
        reference: Any,
        t: float,
        slice_dim: int | None = None,
        slice_value: float | None = None,
        slice_states: torch.Tensor | None = None,
        slice_values: torch.Tensor | None = None,
    ) -> None:
        self.t = float(t)
        #: the reference's system: a trainer or evaluation refuses a candidate of other physics
        self.system = getattr(reference, "system", None)
        pts = reference.grid.points(torch.float32)
        self.volume_states = pts.reshape(-1, pts.shape[-1])
        self.volume_values = reference.value(self.volume_states, self.t)
        if slice_states is None:
            if slice_dim is None or slice_value is None:
                dim, value = self.system.reference_slice()
                slice_dim = dim if slice_dim is None else slice_dim
                slice_value = value if slice_value is None else slice_value
            axis = reference.grid.axis(slice_dim)
            k = int(torch.argmin((axis - slice_value).abs()))
            slice_states = pts.select(slice_dim, k).reshape(-1, pts.shape[-1])
            slice_values = reference.value(slice_states, self.t)
        self.slice_states, self.slice_values = slice_states.float(), slice_values.float()

    def __call__(self, candidate: Any) -> dict[str, float]:
        if self.system is not None:
            self.system.require_same_physics(candidate.system, "the evaluated value function")
        with torch.no_grad():
            vol = compare(candidate, self.volume_values, self.volume_states, self.t)
            sl = compare(candidate, self.slice_values, self.slice_states, self.t)
        return {"mse_volume": vol["mse"], "iou_volume": vol["iou"], "mse_slice": sl["mse"], "iou_slice": sl["iou"]}
