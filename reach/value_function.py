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


def time_range(vf: object) -> tuple[float, float] | None:
    """The times-to-go ``(low, high)`` a value function can be trusted at, or None if it does not say.

    Networks are trained on ``[0, horizon]`` and grid solutions store a range of times; outside it a
    network extrapolates and a grid cannot interpolate, so both refuse such times."""
    rng = getattr(vf, "time_range", None)
    return None if rng is None else (float(rng[0]), float(rng[1]))


def check_time(t: float | torch.Tensor, low: float, high: float) -> None:
    """Raise ``ValueError`` unless every time-to-go in ``t`` is finite and in ``[low, high]``.

    A relative tolerance of 1e-6 admits times computed in float32 (``k * dt`` summed up)."""
    tt = torch.as_tensor(t, dtype=torch.float64)
    tol = 1e-6 * max(1.0, abs(high))
    bad = ~torch.isfinite(tt) | (tt < low - tol) | (tt > high + tol)
    if bool(bad.any()):
        value = tt[bad].reshape(-1)[0].item() if tt.ndim else tt.item()
        raise ValueError(
            f"time-to-go t = {value} lies outside [{low:g}, {high:g}], the times this value function covers "
            "(networks are trained on [0, horizon]; grid solutions store a range of times)"
        )


def check_time_coverage(vf: object, low: float, high: float, what: str) -> None:
    """Raise before any work if ``vf`` does not cover the times-to-go ``[low, high]`` that ``what`` needs."""
    rng = time_range(vf)
    if rng is None:
        return
    tol = 1e-6 * max(1.0, abs(high))
    if low < rng[0] - tol or high > rng[1] + tol:
        raise ValueError(
            f"{what} needs times-to-go [{low:g}, {high:g}], but the value function covers only [{rng[0]:g}, {rng[1]:g}]"
            + (" (solve the grid with --times from 0, e.g. the default of reach groundtruth)" if rng[0] > low else "")
        )
