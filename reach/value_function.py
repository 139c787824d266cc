"""The value-function interface that grid solutions and neural networks both implement.

Safety code (policies, filters, rollouts, verification) takes any :class:`ValueFunction`, so a grid
solution can stand in for a learned network as the reference policy or a control experiment.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

from reach.systems.base import ControlAffineSystem


@runtime_checkable
class ValueFunction(Protocol):
    """``V(x, t)`` of a system, with ``t`` the time-to-go; batched over leading dimensions.

    ``value(x, t)`` maps states ``(..., n)`` to ``(...)`` and ``gradient(x, t)`` to ``(..., n)``;
    ``t`` is a float or a tensor broadcastable to the batch. Both run on ``x``'s device and dtype.
    """

    system: ControlAffineSystem

    def value(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor: ...

    def gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor: ...
