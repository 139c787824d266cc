"""The Hamiltonian and the optimal inputs, derived once from a system's declared physics.

From ``f``, ``G_u``, ``G_d``, the input sets and the players' objectives (:mod:`reach.systems.problem`),
on columns with a backend (:mod:`reach.systems.arrays`):

* ``xdot = f(x) + G_u(x) u + G_d(x) d``;
* the switching functions ``G^T p`` and the optimal inputs, extreme points of the input sets
  (tie-break: the centre of the set where a switching function is zero);
* the Hamiltonian ``H(x, p) = opt_u opt_d p . xdot`` in closed form
  (:class:`~reach.systems.hamiltonian.FixedStateHamiltonian` for many costates at fixed states);
* the per-dimension bound on ``|dH/dp_i|`` (the grid solver's Lax-Friedrichs dissipation) and the
  wrapping of periodic dimensions.

Why a module of its own: these are the derived parts every solver, trainer and filter calls; the
declarations they read stay in :class:`~reach.systems.base.ControlAffineSystem`, which inherits
:class:`OptimalInputs`.
"""

from __future__ import annotations

from collections.abc import Sequence

from reach.systems.arrays import FLOAT, Backend, Column, InputMatrix, is_number
from reach.systems.box import Ball, InputSet
from reach.systems.hamiltonian import FixedStateHamiltonian
from reach.systems.problem import Objective


def _radius(bounds: InputSet) -> float | None:
    """A ball's radius, ``None`` for a box (the Hamiltonian's side descriptor)."""
    return float(bounds.radius) if isinstance(bounds, Ball) else None


class OptimalInputs:
    """Dynamics, optimal inputs, Hamiltonian and dissipation on columns, for a
    :class:`~reach.systems.base.ControlAffineSystem` (which declares the physics these read:
    ``drift``, ``control_matrix``, ``disturbance_matrix``, the input sets, the objectives)."""

    def xdot_columns(self, x: Sequence[Column], u: Sequence[Column], d: Sequence[Column], xp: Backend) -> list[Column]:
        """``f(x) + G_u(x) u + G_d(x) d`` on columns."""
        # Hot path of every simulation step: kept free of avoidable calls and copies.
        out = self.drift(x, xp)
        for (i, j), g in self.control_matrix(x, xp).items():
            out[i] = out[i] + g * u[j]
        if d:
            for (i, k), g in self.disturbance_matrix(x, xp).items():
                out[i] = out[i] + g * d[k]
        return out

    @staticmethod
    def _switching(matrix: InputMatrix, p: Sequence[Column], dim: int) -> list[Column]:
        """``G^T p``: one switching function per input dimension."""
        s: list[Column | None] = [None] * dim
        for (i, j), g in matrix.items():
            term = p[i] if is_number(g, 1.0) else g * p[i]  # skip passes that change nothing (the grid
            s[j] = term if s[j] is None else s[j] + term  # solver runs these on every node, every stage)
        return [0.0 if sj is None else sj for sj in s]

    def _optimal(self, s: Sequence[Column], box: InputSet, objective: Objective, xp: Backend) -> list[Column]:
        sigma = 1.0 if objective == "max" else -1.0
        if isinstance(box, Ball):  # c + sigma r s / |s|_2; the centre where s = 0
            numbers = all(isinstance(sj, (int, float)) for sj in s)
            norm = FLOAT.norm(s) if numbers else xp.norm(list(s))
            if numbers:
                return [c + (sigma * box.radius * sj / norm if norm > 0 else 0.0) for sj, c in zip(s, box.center)]
            safe = xp.where(norm > 0, norm, 1.0)
            return [c + sigma * box.radius * sj / safe for sj, c in zip(s, box.center)]
        return [c + sigma * h * xp.sign(sj) for sj, c, h in zip(s, box.center, box.half_width)]

    def optimal_inputs_columns(
        self, x: Sequence[Column], p: Sequence[Column], xp: Backend
    ) -> tuple[list[Column], list[Column]]:
        """Optimal control and disturbance for costate ``p`` (tie-break: box centre)."""
        su = self._switching(self.control_matrix(x, xp), p, self.control_dim)
        u = self._optimal(su, self.control_bounds, self.control_objective, xp)
        d: list[Column] = []
        if self.disturbance_dim:
            sd = self._switching(self.disturbance_matrix(x, xp), p, self.disturbance_dim)
            d = self._optimal(sd, self.disturbance_bounds, self.disturbance_objective, xp)
        return u, d

    def hamiltonian_columns(self, x: Sequence[Column], p: Sequence[Column], xp: Backend) -> Column:
        """``H(x, p) = opt_u opt_d p . xdot`` in closed form for box inputs."""
        return self.hamiltonian_at(x, xp)(p)

    def hamiltonian_at(
        self, x: Sequence[Column], xp: Backend, *, scale: Sequence[float] | None = None, prune: bool = False
    ) -> FixedStateHamiltonian:
        """``p -> H(x, scale * p)`` with the drift and input matrices evaluated once at the states ``x``.

        For callers that read ``H`` at the same states many times (the grid solver). ``prune`` drops
        drift and matrix entries that are zero at every state (it reads each array column once);
        ``scale`` folds a number factor per costate component into the coefficients.
        """
        sides = [(self.control_matrix(x, xp), self.control_bounds, self.control_objective)]
        if self.disturbance_dim:
            sides.append((self.disturbance_matrix(x, xp), self.disturbance_bounds, self.disturbance_objective))
        return FixedStateHamiltonian(
            self.drift(x, xp),
            [
                (m, box.center, box.half_width, 1.0 if objective == "max" else -1.0, _radius(box))
                for m, box, objective in sides
            ],
            xp,
            scale=scale,
            prune=prune,
        )

    def dissipation_columns(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        """``max over the input boxes of |xdot_i|`` per state dimension: bounds ``|dH/dp_i|``. A ball of
        inputs counts as its bounding box, which contains it: still a bound, if not the tightest."""
        centre_u = self.control_bounds.center
        centre_d = self.disturbance_bounds.center
        out = list(self.xdot_columns(x, centre_u, centre_d, xp))
        out = [xp.abs(v) if not isinstance(v, (int, float)) else abs(v) for v in out]
        sides = [(self.control_matrix(x, xp), self.control_bounds)]
        if self.disturbance_dim:
            sides.append((self.disturbance_matrix(x, xp), self.disturbance_bounds))
        for matrix, box in sides:
            hw = box.half_width
            for (i, j), g in matrix.items():
                out[i] = out[i] + (xp.abs(g) if not isinstance(g, (int, float)) else abs(g)) * hw[j]
        return out

    def wrap_columns(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        """Periodic dimensions wrapped into ``[-pi, pi)``; others unchanged."""
        out = list(x)
        wrap = xp.wrap_angle
        for i in self.periodic_dims:
            out[i] = wrap(out[i])
        return out
