"""The inputs a value function induces: from its gradient, or from a held step of its values.

``u*(x, t)`` and ``d*(x, t)`` come from ``p = grad V(x, t)`` through the system's derived
:meth:`~reach.systems.base.ControlAffineSystem.optimal_control` and ``optimal_disturbance``, so
the sign conventions live in one place (the system), whatever produced ``V``.
:class:`GreedyPolicy` picks instead, among held candidate inputs, the one that leaves the most
value after a short step (the dynamic programming principle; it commits to one manoeuvre where
``grad V`` blends two).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
import torch

from reach.integrators import check_integrator, make_stepper
from reach.systems.arrays import TORCH
from reach.systems.box import require_box
from reach.validation import is_positive_finite
from reach.value_function import ValueFunction, value_and_gradient
from safety.tracing import refuse_untrusted


def check_states(x: torch.Tensor, state_dim: int, what: str = "states") -> None:
    """Raise ``ValueError`` for a wrong shape, a tensor that holds no real values (an integer or bool
    dtype, the meta device) or a NaN/inf entry, naming the first bad state."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{what} must be a torch.Tensor, got {type(x).__name__}")
    if not x.dtype.is_floating_point:
        raise ValueError(f"{what} must be a floating-point tensor (float32 or float64), got {x.dtype}")
    if x.is_meta:
        raise ValueError(f"{what} are on the meta device, which holds no values")
    if x.ndim == 0 or x.shape[-1] != state_dim:
        raise ValueError(f"{what} must have shape (..., {state_dim}), got {tuple(x.shape)}")
    finite = torch.isfinite(x).all(-1)
    refuse_untrusted(~finite, lambda: f"{what} contain NaN or inf, e.g. {x[~finite][0].tolist()}")


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


#: the policies a value function induces: ``"gradient"`` (the bang-bang ``u*`` of ``grad V``, the
#: HJ optimal control and DeepReach's) and ``"greedy"`` (:class:`GreedyPolicy`)
POLICIES = ("gradient", "greedy")

#: how long (s) :class:`GreedyPolicy` holds each candidate input before it reads ``V``
GREEDY_STEP = 0.05

#: the most candidate inputs :class:`GreedyPolicy` tries per state (``2^m_u + 1``: m_u <= 10)
GREEDY_MAX_CANDIDATES = 1025


def check_policy(policy: object) -> str:
    """``policy`` if it names one of :data:`POLICIES`, else ``ValueError`` naming it."""
    if not isinstance(policy, str) or policy not in POLICIES:
        raise ValueError(f"policy must be one of {POLICIES}, got {policy!r}")
    return policy


class GreedyPolicy:
    """The dynamic-programming step of the value function, over a finite set of held inputs.

    ``u(x, t) = argmax_c min_d [ min( V(y(step), t - step), min_{s <= step} l(y(s)) ) ]``: each
    candidate control ``c`` (the control box's corners and its centre) is held for ``step`` seconds
    from ``x``, against each candidate disturbance ``d`` (the box's corners and the gradient's
    ``d*``; none without a disturbance), and the candidate whose worst path ends with the most
    ``min(V, l)`` is applied. The HJ dynamic programming principle says the optimal value satisfies
    this with equality as ``step -> 0``, where it becomes the gradient's ``u*``.

    Why: at a kink of ``V`` (two manoeuvres tie, e.g. three cars converging that can all turn left
    or all turn right) ``grad V`` is a blend of the two, and the bang-bang ``u*`` built from it can
    pick neither: each car turns by the sign of its own partial derivative, into the others. A held
    step commits to one manoeuvre. Such policy errors, where some held input avoids the collision
    that ``u*`` runs into, are among the shipped 9D model's false-safe states (measured:
    docs/results/verification.md, *Value errors and policy errors*).

    Costs ``(2^m_u + 1) x (disturbance candidates)`` value evaluations and ``step / dt`` integration
    substeps per decision, against one value-and-gradient evaluation for ``u*``. Ties go to the
    first candidate (the centre). ``V`` is read wherever the value function answers, as ``u*`` reads
    ``grad V``. A non-finite value or margin raises ``ValueError``.
    """

    def __init__(
        self,
        value_function: ValueFunction,
        step: float = GREEDY_STEP,
        dt: float = 0.0025,
        integrator: str = "euler",
    ) -> None:
        for name, v in (("step", step), ("dt", dt)):
            if not is_positive_finite(v):
                raise ValueError(f"the greedy policy's {name} must be a finite number > 0, got {v!r}")
        system = value_function.system
        corners = 2**system.control_dim + 1
        if corners > GREEDY_MAX_CANDIDATES:
            raise ValueError(
                f"the greedy policy tries 2^m + 1 = {corners} inputs per state for {system.control_dim} "
                f"control inputs; at most {GREEDY_MAX_CANDIDATES} (10 inputs) are supported"
            )
        self.value_function = value_function
        self.system = system
        self.step = float(step)
        self.substeps = max(1, math.ceil(self.step / float(dt) - 1e-9))
        self._advance = make_stepper(system, self.step / self.substeps, check_integrator(integrator), TORCH)
        box = require_box(system.control_bounds, "the greedy policy")
        require_box(system.disturbance_bounds, "the greedy policy")
        self._controls = torch.tensor([box.center, *itertools.product(*zip(box.low, box.high))], dtype=torch.float64)
        self._disturbances = (
            torch.tensor(list(itertools.product(*zip(system.disturbance_bounds.low, system.disturbance_bounds.high))))
            if system.disturbance_dim
            else None
        )

    def control(self, x: torch.Tensor, t: float | torch.Tensor, d_star: torch.Tensor | None = None) -> torch.Tensor:
        """The greedy inputs ``(..., m_u)`` at states ``(..., n)``; ``d_star`` (same batch) joins the
        disturbance candidates where the system has a disturbance."""
        system = self.system
        n, m = system.state_dim, system.control_dim
        batch = x.shape[:-1]
        flat = x.reshape(-1, n)
        count = flat.shape[0]
        controls = self._controls.to(dtype=flat.dtype, device=flat.device)
        if self._disturbances is None:
            dists = None
            paths = 1
        else:
            corners = self._disturbances.to(dtype=flat.dtype, device=flat.device)
            per_state = corners.unsqueeze(1).expand(-1, count, -1)  # (J, N, m_d)
            if d_star is not None:
                per_state = torch.cat([per_state, d_star.reshape(1, count, -1).to(flat.dtype)])
            paths = per_state.shape[0]
            dists = per_state.reshape(1, paths * count, -1).expand(len(controls), -1, -1)
            dists = dists.reshape(-1, system.disturbance_dim)
        k = len(controls)
        # (K, J, N) candidates, flattened in that order
        y = flat.unsqueeze(0).expand(k * paths, -1, -1).reshape(-1, n)
        u = controls.repeat_interleave(paths * count, 0)
        uc = system.input_columns(u, system.control_bounds, "u")
        dc = system.input_columns(dists, system.disturbance_bounds, "d")
        low = system.failure_margin(y)
        cols = TORCH.unbind(y)  # the held step stays in columns: one stack at its end
        for _ in range(self.substeps):
            cols = self._advance(cols, uc, dc)
            low = torch.minimum(low, system.failure_margin_columns(cols, TORCH))
        y = TORCH.stack(cols, like=low)
        if isinstance(t, torch.Tensor) and t.ndim:
            t_after = (t.reshape(-1).expand(count) - self.step).clamp_min(0.0).repeat(k * paths)
        else:
            t_after = max(float(t) - self.step, 0.0)
        # V wherever the value function answers, as u* uses grad V there (a network extrapolates
        # beyond its training box, a grid takes its edge value): scoring l alone outside the domain
        # would steer by the margin's one-step gain, and lost 32 of 20,000 9D states u* kept safe
        v = self.value_function.value(y, t_after).to(low.dtype)
        # an infinite V would hide behind min(V, l): each value is checked, not only the score
        trusted = torch.isfinite(v) & torch.isfinite(low)
        score = torch.minimum(v, low).reshape(k, paths, count).amin(1)
        finite = trusted.reshape(k, paths, count).all(0).all(0)
        refuse_untrusted(
            ~finite,
            lambda: (
                f"the greedy policy met a non-finite value predicted from state {flat[~finite][0].tolist()} (t = {t})"
            ),
        )
        best = score.argmax(0)
        return controls[best].to(x.dtype).reshape(*batch, m)


def worst_case_disturbance(
    value_function: ValueFunction, time_to_go: float | None = None
) -> Callable[[np.ndarray], np.ndarray]:
    """A scene disturbance ``state -> d*`` (NumPy in, NumPy out) that attacks with the value
    function's optimal disturbance at ``time_to_go`` (the system's horizon by default)."""
    policy = OptimalPolicy(value_function)
    t = value_function.system.horizon if time_to_go is None else float(time_to_go)

    def attack(x: np.ndarray) -> np.ndarray:
        return policy.disturbance(torch.as_tensor(x, dtype=torch.float64), t).numpy()

    return attack
