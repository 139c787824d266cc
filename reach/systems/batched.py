"""The batched torch interface of a system: states, inputs and costates as tensors ``(..., n)``.

Each method checks its tensors' shapes and calls the column form (:mod:`reach.systems.optimal_inputs`,
the declared margins) on torch columns: dynamics, Hamiltonian, optimal inputs, switching functions,
dissipation bounds, margins, boundary value, wrapping, and uniform sampling of the domain.

Why a module of its own: this is the interface the rest of the library calls with tensors, apart
from the physics declarations of :class:`~reach.systems.base.ControlAffineSystem` (which inherits
:class:`BatchedPhysics`) and from the column-level derivations.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from reach.systems.arrays import FLOAT, TORCH, Column
from reach.systems.box import Box


class BatchedPhysics:
    """Batched torch methods of a :class:`~reach.systems.base.ControlAffineSystem`: each checks its
    tensors and runs the system's column form on torch columns."""

    def _check(self, name: str, t: torch.Tensor, dim: int) -> None:
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{self.name}: {name} must be a torch.Tensor, got {type(t).__name__}")
        if t.ndim == 0 or t.shape[-1] != dim:
            raise ValueError(f"{self.name}: {name} must have shape (..., {dim}), got {tuple(t.shape)}")

    def input_columns(self, v: torch.Tensor | None, box: Box, name: str) -> Sequence[Column]:
        """Columns of a batch of inputs ``(..., box.dim)`` (checked), or the box centre for None."""
        if v is None:
            return box.center
        self._check(name, v, box.dim)
        return TORCH.unbind(v)

    def dynamics(self, x: torch.Tensor, u: torch.Tensor | None = None, d: torch.Tensor | None = None) -> torch.Tensor:
        """``x'`` for states ``(..., n)``, controls ``(..., m_u)`` and disturbances ``(..., m_d)``.

        A missing input means the centre of its box (zero turn rate for the built-in systems).
        """
        self._check("x", x, self.state_dim)
        cols = TORCH.unbind(x)
        uc = self.input_columns(u, self.control_bounds, "u")
        dc = self.input_columns(d, self.disturbance_bounds, "d")
        return TORCH.stack(self.xdot_columns(cols, uc, dc, TORCH), like=cols[0])

    def hamiltonian(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """``H(x, p)`` for states and costates ``(..., n)``; returns ``(...)``."""
        self._check("x", x, self.state_dim)
        self._check("p", p, self.state_dim)
        h = self.hamiltonian_columns(TORCH.unbind(x), TORCH.unbind(p), TORCH)
        return h if isinstance(h, torch.Tensor) else torch.full(x.shape[:-1], float(h), dtype=x.dtype, device=x.device)

    def optimal_control(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """``u*(x, p)``, shape ``(..., m_u)``: the box corner along ``G_u^T p`` (centre on ties)."""
        self._check("x", x, self.state_dim)
        self._check("p", p, self.state_dim)
        u, _ = self.optimal_inputs_columns(TORCH.unbind(x), TORCH.unbind(p), TORCH)
        return TORCH.stack(u, like=x[..., 0])

    def control_switching(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """``G_u(x)^T p``, shape ``(..., m_u)``: how ``p . xdot`` changes with each control input
        (``p . f(x, u, d)`` is affine in ``u`` with this slope)."""
        self._check("x", x, self.state_dim)
        self._check("p", p, self.state_dim)
        s = self._switching(self.control_matrix(TORCH.unbind(x), TORCH), TORCH.unbind(p), self.control_dim)
        return TORCH.stack(s, like=x[..., 0])

    def optimal_disturbance(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """``d*(x, p)``, shape ``(..., m_d)`` (``m_d`` may be 0)."""
        self._check("x", x, self.state_dim)
        self._check("p", p, self.state_dim)
        if not self.disturbance_dim:
            return x.new_zeros((*x.shape[:-1], 0))
        _, d = self.optimal_inputs_columns(TORCH.unbind(x), TORCH.unbind(p), TORCH)
        return TORCH.stack(d, like=x[..., 0])

    def dissipation_bounds(self, x: torch.Tensor) -> torch.Tensor:
        """Per-dimension bound on ``|dH/dp_i|`` at each state, shape ``(..., n)``."""
        self._check("x", x, self.state_dim)
        return TORCH.stack(self.dissipation_columns(TORCH.unbind(x), TORCH), like=x[..., 0])

    def failure_margin(self, x: torch.Tensor) -> torch.Tensor:
        """``l(x)`` for states ``(..., n)``; returns ``(...)``."""
        self._check("x", x, self.state_dim)
        return self.failure_margin_columns(TORCH.unbind(x), TORCH)

    def target_margin(self, x: torch.Tensor) -> torch.Tensor:
        """``l(x)`` of a reach kind for batched states ``(..., n)``: negative inside the target."""
        return self.target_margin_columns(TORCH.unbind(x), TORCH)

    def constraint_margin(self, x: torch.Tensor) -> torch.Tensor:
        """``g(x)`` of a reach-avoid system for batched states ``(..., n)``: positive where allowed."""
        return self.constraint_margin_columns(TORCH.unbind(x), TORCH)

    def terminal_margin(self, x: torch.Tensor) -> torch.Tensor:
        """The ``l`` of the kind's variational inequality for batched states ``(..., n)``: the failure
        margin (avoid) or the target margin (reach kinds)."""
        self._check("x", x, self.state_dim)
        return self.terminal_margin_columns(TORCH.unbind(x), TORCH)

    def boundary_value(self, x: torch.Tensor) -> torch.Tensor:
        """``V(x, 0)`` for batched states ``(..., n)``: ``l(x)``, or ``max(l(x), -g(x))`` for reach-avoid."""
        g = self.constraint_margin(x) if self.problem.has_constraint else None
        return self.problem.boundary_value(self.terminal_margin(x), g)

    def wrap(self, x: torch.Tensor) -> torch.Tensor:
        """States with periodic dimensions wrapped into ``[-pi, pi)``."""
        self._check("x", x, self.state_dim)
        cols = TORCH.unbind(x)
        return TORCH.stack(self.wrap_columns(cols, TORCH), like=cols[0])

    # ------------------------------------------------------------------ sampling helpers
    def domain_tensor(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
        """The domain as a ``(n, 2)`` tensor of (low, high)."""
        return torch.tensor(self.domain, dtype=dtype, device=device)

    def sample_states(
        self,
        n: int,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
    ) -> torch.Tensor:
        """``n`` states drawn uniformly from the domain (batched; no loop over samples)."""
        box = self.domain_tensor(dtype, device)
        r = torch.rand((n, self.state_dim), generator=generator, dtype=dtype, device=device)
        return box[:, 0] + r * (box[:, 1] - box[:, 0])

    def sample_states_numpy(self, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
        """States drawn uniformly from the domain with a NumPy generator (float64)."""
        lo, hi = np.array(self.domain, dtype=np.float64).T
        size = (self.state_dim,) if n is None else (n, self.state_dim)
        return rng.uniform(lo, hi, size=size)

    def failure_margin_float(self, x: Sequence[float]) -> float:
        """``l(x)`` for one state given as a sequence of floats."""
        return float(self.failure_margin_columns(x, FLOAT))
