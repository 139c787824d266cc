"""Every conflict of a batch as one sparse quadratic program, solved by Clarabel in one call.

Each conflict asks for the turn rates closest to the nominal ones that keep each of its pairs'
linear conditions (:mod:`safety.fleet.filter` writes them) within the turn bounds:

``minimise sum (w_k - w_nom_k)^2  s.t.  c_p . w >= r_p  (every pair p),  |w_k| <= w_max_k``.

Conflicts share no cars, so stacking them gives one block-diagonal problem, solved in one call
instead of one call per conflict. A conflict whose conditions no input meets would make the whole
problem infeasible, so each condition gets a slack ``s_p >= 0`` priced by an exact L1 penalty
``rho * s_p``: for ``rho`` above the largest multiplier the slacks are 0 wherever the conditions can
be met, and a positive slack marks the conflict that cannot (its rule then is the caller's
fallback). Rows are scaled to unit length first, so slacks and multipliers are in one unit (the
multipliers of unit rows are at most a few times the largest turn-rate change, far below the
default ``rho``).

**Why Clarabel** (interior point), against OSQP (ADMM) on the same saved problems
(``benchmarks/fleet_qp_solvers.py``, numbers on docs/results with their command): an interior-point
method ends with constraint violations at its tolerance, near 1e-9, where ADMM's first-order
iterations stop at a looser residual unless polished, and a safety condition is a constraint one
must meet, not approximately; Clarabel also needs no warm start or tuning of a step parameter, and
its cost grows gently with the problem's size for these small sparse blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

__all__ = ["ConflictQP", "QPSolution", "solve"]


@dataclass(frozen=True)
class ConflictQP:
    """The stacked problem, as NumPy arrays (float64).

    Attributes:
        nominal, bound: ``(V,)`` each variable's nominal value and bound ``|w| <= bound``.
        columns: ``(C, 2)`` long: the variables of each condition (``-1``: none).
        coefficients: ``(C, 2)`` their coefficients; ``rhs``: ``(C,)``: ``c . w >= rhs``.
        penalty: the L1 price of a slack (per unit of a unit-scaled row).
    """

    nominal: np.ndarray
    bound: np.ndarray
    columns: np.ndarray
    coefficients: np.ndarray
    rhs: np.ndarray
    penalty: float = 1e3

    @property
    def sizes(self) -> tuple[int, int]:
        """``(variables, conditions)``."""
        return int(self.nominal.shape[0]), int(self.rhs.shape[0])

    def scaled(self) -> tuple[np.ndarray, np.ndarray]:
        """The coefficients and right-hand sides divided by each row's length (a row of zero
        coefficients keeps its right-hand side: met or not whatever the input)."""
        norm = np.sqrt((self.coefficients**2).sum(1))
        scale = np.where(norm > 1e-12, norm, 1.0)
        return self.coefficients / scale[:, None], self.rhs / scale

    def matrices(self) -> tuple[sparse.csc_matrix, np.ndarray, sparse.csc_matrix, np.ndarray]:
        """``(P, q, A, b)`` of ``min 1/2 z'Pz + q'z  s.t.  b - A z >= 0`` with ``z = (w, s)``:
        rows are the conditions, the slacks' signs, then the upper and lower bounds."""
        nv, nc = self.sizes
        coef, rhs = self.scaled()
        p = sparse.csc_matrix(
            (np.full(nv, 2.0), np.arange(nv), np.r_[np.arange(nv + 1), np.full(nc, nv)]), shape=(nv + nc, nv + nc)
        )
        q = np.r_[-2.0 * self.nominal, np.full(nc, float(self.penalty))]
        used = self.columns >= 0
        rows = np.broadcast_to(np.arange(nc)[:, None], self.columns.shape)[used]
        # one set of triplets, converted once: -c . w - s <= -rhs; -s <= 0; w <= bound; -w <= bound
        ar, av = np.arange(nc), np.arange(nv)
        r = np.concatenate([rows, ar, nc + ar, 2 * nc + av, 2 * nc + nv + av])
        c = np.concatenate([self.columns[used], nv + ar, nv + ar, av, av])
        v = np.concatenate([-coef[used], -np.ones(2 * nc), np.ones(nv), -np.ones(nv)])
        a = sparse.csc_matrix((v, (r, c)), shape=(2 * nc + 2 * nv, nv + nc))
        b = np.r_[-rhs, np.zeros(nc), self.bound, self.bound]
        return p, q, a, b

    def violation(self, w: np.ndarray) -> np.ndarray:
        """``(C,)`` how far each condition is from met by ``w`` (unit-scaled rows; 0 where met)."""
        coef, rhs = self.scaled()
        cols = np.where(self.columns >= 0, self.columns, 0)
        lhs = (np.where(self.columns >= 0, coef, 0.0) * w[cols]).sum(1) if w.size else np.zeros(len(rhs))
        return np.maximum(rhs - lhs, 0.0)


@dataclass(frozen=True)
class QPSolution:
    """``w``: ``(V,)`` the inputs (clipped to the bounds); ``slack``: ``(C,)`` per condition (``>=
    0``); ``solved``: whether the solver reported an optimum (else every conflict falls back)."""

    w: np.ndarray
    slack: np.ndarray
    solved: bool
    status: str


def solve(qp: ConflictQP) -> QPSolution:
    """Solve the stacked problem with Clarabel, on one thread, in one call."""
    import clarabel  # lazy: only a decision with a conflict of two or more active pairs needs it

    nv, nc = qp.sizes
    if nv == 0 and nc == 0:
        return QPSolution(np.zeros(0), np.zeros(0), True, "empty")
    p, q, a, b = qp.matrices()
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.max_threads = 1
    solver = clarabel.DefaultSolver(p, q, a, b, [clarabel.NonnegativeConeT(a.shape[0])], settings)
    out = solver.solve()
    status = str(out.status)
    solved = status in ("Solved", "AlmostSolved", "SolverStatus.Solved")
    z = np.asarray(out.x, dtype=np.float64)
    if not solved or z.shape[0] != nv + nc or not np.isfinite(z).all():
        return QPSolution(np.zeros(nv), np.full(nc, np.inf), False, status)
    w = np.clip(z[:nv], -qp.bound, qp.bound)
    return QPSolution(w, np.maximum(z[nv:], 0.0), True, status)
