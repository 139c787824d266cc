"""Optimal control and disturbance from a value function's gradient.

``u*(x, t)`` and ``d*(x, t)`` come from ``p = grad V(x, t)`` through the system's derived
:meth:`~reach.systems.base.ControlAffineSystem.optimal_control` and ``optimal_disturbance``, so
the sign conventions live in one place (the system), whatever produced ``V``.
"""

from __future__ import annotations

import torch

from reach.value_function import ValueFunction, value_and_gradient


def check_states(x: torch.Tensor, state_dim: int, what: str = "states") -> None:
    """Raise ``ValueError`` for a wrong shape or a NaN/inf entry, naming the first bad state."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{what} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim == 0 or x.shape[-1] != state_dim:
        raise ValueError(f"{what} must have shape (..., {state_dim}), got {tuple(x.shape)}")
    finite = torch.isfinite(x).all(-1)
    if not bool(finite.all()):
        bad = x[~finite][0].tolist()
        raise ValueError(f"{what} contain NaN or inf, e.g. {bad}")


class OptimalPolicy:
    """The optimal inputs of a value function: ``inputs(x, t) -> (V, u*, d*)``, and with the costate,
    ``evaluate(x, t) -> (V, grad V, u*, d*)`` (for the filters, which also need ``grad V``)."""

    def __init__(self, value_function: ValueFunction) -> None:
        self.value_function = value_function
        self.system = value_function.system

    def evaluate(
        self, x: torch.Tensor, t: float | torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``V(x, t)``, ``p = grad V``, ``u*`` ``(..., m_u)`` and ``d*`` ``(..., m_d)`` from one gradient evaluation."""
        check_states(x, self.system.state_dim)
        v, p = value_and_gradient(self.value_function, x, t)
        return v, p, self.system.optimal_control(x, p), self.system.optimal_disturbance(x, p)

    def inputs(self, x: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``V(x, t)``, ``u*`` ``(..., m_u)`` and ``d*`` ``(..., m_d)`` from one gradient evaluation."""
        v, _, u, d = self.evaluate(x, t)
        return v, u, d

    def control(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        return self.inputs(x, t)[1]

    def disturbance(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        return self.inputs(x, t)[2]
