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

    Network input is ``(t, (x - state_offset) / state_scale)``, followed by ``extra_inputs`` zeros
    (DeepReach's ``RocketLanding`` appends one); the value is ``value_scale * output + value_offset``
    for a ``"vanilla"`` model (DeepReach 2021, the seed authors' checkpoints) and
    ``value_scale * output + b(x)`` for a ``"diff"`` one (``diff_model=True``, every system of
    DeepReach's public release), ``b`` the system's boundary value.
    """

    state_offset: tuple[float, ...]
    state_scale: tuple[float, ...]
    value_scale: float = 25.0
    value_offset: float = 0.25
    model: str = "vanilla"
    extra_inputs: int = 0

    def __post_init__(self) -> None:
        if self.model not in ("vanilla", "diff"):
            raise ValueError(f"DeepReachNormalisation: model must be 'vanilla' or 'diff', got {self.model!r}")
        if isinstance(self.extra_inputs, bool) or not isinstance(self.extra_inputs, int) or self.extra_inputs < 0:
            raise ValueError(f"DeepReachNormalisation: extra_inputs must be an integer >= 0, got {self.extra_inputs!r}")
