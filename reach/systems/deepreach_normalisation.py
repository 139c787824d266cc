"""DeepReach's input and output scaling, declared by systems only so that a DeepReach checkpoint imports.

It lives in the base layer, beside the systems that declare it (``Air3D``, the multi-vehicle family),
because :mod:`training` sits above them. Its one use: :func:`training.deepreach.load_deepreach` builds
the imported network's encoding from it (``Encoding.deepreach``); our own networks scale their inputs
from a system's ``domain`` and never read it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DeepReachNormalisation:
    """How DeepReach maps states and values to network inputs and outputs, for importing its
    checkpoints only (see :func:`training.deepreach.load_deepreach`).

    Network input is ``(t, (x - state_offset) / state_scale)``; the value is
    ``value_scale * output + value_offset``.
    """

    state_offset: tuple[float, ...]
    state_scale: tuple[float, ...]
    value_scale: float = 25.0
    value_offset: float = 0.25
