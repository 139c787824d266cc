"""The one place where a dynamical system is defined, and everything derived from it.

A concrete system declares only physics (see :class:`ControlAffineSystem`): its state layout, the
control-affine dynamics ``x' = f(x) + G_u(x) u + G_d(x) d`` with box-bounded inputs, which player
maximises the value, the failure margin ``l(x)`` and a default horizon. Everything the rest of the
library needs is derived here, once, generically:

* the Hamiltonian ``H(x, p) = opt_u opt_d p . (f + G_u u + G_d d)``,
* the optimal control and disturbance (extreme points of the input boxes),
* the per-dimension bound on ``|dH/dp_i|`` used as Lax-Friedrichs dissipation by the grid solver,
* batched dynamics, failure margin and heading wrapping.

Physics methods work on *columns* with a backend (:mod:`reach.systems.arrays`), so the same
lines run on Python floats (single environment), NumPy (vector environments) and torch (solver,
training, safety; any dtype and device, differentiable). Public batched methods take torch
tensors shaped ``(..., n)``.

Conventions (see docs/concepts.md): ``t`` is time-to-go, the backward reachable tube is
``{x : V(x, t) <= 0}``, ``l(x) < 0`` inside the failure set, the control keeps the system safe by
maximising ``p . f`` and the disturbance attacks by minimising it.

**Tie-break.** Where a switching function ``s = G^T p`` is exactly zero, every input of the box is
optimal for the Hamiltonian; the library then returns the *centre* of the box (0 for a symmetric
turn-rate box). This is what ``sign(0) == 0`` gives in ``u* = c + h sign(s)``, it matches DeepReach's
``torch.sign`` convention, and it introduces no bias toward either side.
"""

from __future__ import annotations

import json
import math
from abc import ABCMeta, abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from reach.systems.arrays import FLOAT, TORCH, Backend, Column, is_number
from reach.systems.box import NO_INPUT, Ball, Box, InputSet  # also importable from here, as before the split
from reach.systems.class_names import system_reference
from reach.systems.deepreach_normalisation import DeepReachNormalisation  # likewise
from reach.systems.hamiltonian import FixedStateHamiltonian
from reach.systems.problem import Objective, ProblemKind, problem_kind
from reach.validation import positive_finite

#: Sparse input matrix: {(state index, input index): entry}; absent entries are zero.
InputMatrix = Mapping[tuple[int, int], Column]


class _CheckedOnConstruction(ABCMeta):
    """Runs :meth:`ControlAffineSystem.validate` after every constructor: a bad definition fails when
    it is built, naming the field, not later inside a solver or a training step."""

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        system = super().__call__(*args, **kwargs)
        system.validate()
        return system


def _radius(bounds: InputSet) -> float | None:
    """A ball's radius, ``None`` for a box (the Hamiltonian's side descriptor)."""
    return float(bounds.radius) if isinstance(bounds, Ball) else None


class ControlAffineSystem(metaclass=_CheckedOnConstruction):
    """Base class of every dynamical system; subclasses declare physics only.

    Subclasses set the class or instance attributes below and implement :meth:`drift`,
    :meth:`control_matrix`, optionally :meth:`disturbance_matrix`, and :meth:`failure_margin_columns`.
    Every instance is checked by :meth:`validate` when it is constructed.
    """

    #: short name (default: the class name in lower case); configs store the registered name or the
    #: import path (:func:`reach.systems.class_names.system_reference`)
    name: ClassVar[str]
    state_names: tuple[str, ...]
    #: (low, high) per state dimension; periodic dimensions span one period [-pi, pi)
    domain: tuple[tuple[float, float], ...]
    periodic: tuple[bool, ...]
    control_bounds: InputSet
    disturbance_bounds: InputSet = NO_INPUT
    #: the kind of problem (:mod:`reach.systems.problem`): ``"avoid"`` (write
    #: :meth:`failure_margin_columns`), ``"reach"`` (write :meth:`target_margin_columns`) or
    #: ``"reach-avoid"`` (both :meth:`target_margin_columns` and :meth:`constraint_margin_columns`).
    #: The players' objectives, the variational inequality and the meaning of ``V <= 0`` follow.
    kind: str = "avoid"
    horizon: float
    #: only for importing DeepReach checkpoints; network inputs are scaled from ``domain``
    deepreach: DeepReachNormalisation | None = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" not in cls.__dict__:
            cls.name = cls.__name__.lower()

    # ------------------------------------------------------------------ physics (subclasses)
    @abstractmethod
    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        """``f(x)`` as a new list with one column per state dimension (callers may modify it)."""

    @abstractmethod
    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        """Nonzero entries of ``G_u(x)``."""

    def disturbance_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        """Nonzero entries of ``G_d(x)``; none by default (no disturbance)."""
        return {}

    def failure_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        """``l(x)``: negative inside the failure set, zero on its boundary (an avoid system writes it).

        A reach-avoid system's failure set is where its constraint fails, so by default this is
        :meth:`constraint_margin_columns`; a reach system has no failure set."""
        if self.problem.has_constraint:
            return self.constraint_margin_columns(x, xp)
        raise NotImplementedError(f"{self.name}: a {self.kind} system declares failure_margin_columns")

    def target_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        """``l(x)`` of a reach or reach-avoid system: negative inside the target, zero on its boundary."""
        raise NotImplementedError(f"{self.name}: a {self.kind} system declares target_margin_columns")

    def constraint_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        """``g(x)`` of a reach-avoid system: positive where the state may be, zero or negative in an
        obstacle (a reach-avoid trajectory must keep it positive until it reaches the target)."""
        raise NotImplementedError(f"{self.name}: a {self.kind} system declares constraint_margin_columns")

    @property
    def problem(self) -> ProblemKind:
        """The :class:`~reach.systems.problem.ProblemKind` of :attr:`kind`."""
        return problem_kind(self.kind, self.name)

    @property
    def control_objective(self) -> Objective:
        """``"max"`` (avoid: the control keeps ``V`` high) or ``"min"`` (reach kinds), from the kind."""
        return self.problem.control_objective

    @property
    def disturbance_objective(self) -> Objective:
        """The disturbance's objective, the opposite of the control's (from the kind)."""
        return self.problem.disturbance_objective

    def terminal_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        """The ``l`` of the kind's variational inequality: the failure margin (avoid) or the target
        margin (reach kinds)."""
        return getattr(self, self.problem.margin_method)(x, xp)

    def require_kind(self, kinds: tuple[str, ...], what: str) -> None:
        """Refuse, naming the kind, a tool that does not (yet) handle this system's kind of problem."""
        if self.kind not in kinds:
            raise ValueError(
                f"{what} handle(s) {' and '.join(kinds)} problems; {self.name} is a {self.kind} problem "
                "(the grid solver solves every kind)"
            )

    def margin_rate_bound(self) -> float | None:
        """A bound on ``|d l(x(t)) / dt|`` along every trajectory with admissible inputs, or ``None``.

        Physics, declared per system where it is known (e.g. the sum of two cars' speeds bounds how
        fast their distance changes). With it, a rollout can stop simulating a trajectory once
        ``l(x) > bound * time_left``: the failure set is then out of reach, whatever the inputs.
        """
        return None

    def margin_step_bound(self, dt: float, integrator: str) -> float | None:
        """``delta``: one step of ``integrator`` over ``dt`` lowers the failure margin by at most this,
        from *every* state (inside the domain or far outside it), with every admissible control and
        disturbance held over the step: ``l(step(x, u, d)) >= l(x) - delta``. ``None`` (the default)
        where no such bound is known for this integrator.

        A proof obligation, declared per system with its argument in the docstring (and checked at
        samples in the tests): a formal certificate (:mod:`safety.formal.verifier`) uses it to treat the
        states far from failure, where the value function is not trusted or not defined, without
        bounding the network there."""
        return None

    def margin_outside_domain(self, scale: float = 1.0) -> float | None:
        """A lower bound of the failure margin ``l`` on every state outside the domain (its periodic
        dimensions aside), or ``None`` (the default) where a state outside may be near failure.
        ``scale``: outside the domain widened that many times about its centre (a certificate's
        ``closure_scale``). With :meth:`margin_step_bound` it lets a certificate accept next states
        that leave the domain."""
        return None

    def margin_floor(self, x: torch.Tensor, time: float) -> torch.Tensor | None:
        """A lower bound of ``l`` over the next ``time`` seconds from states ``x`` ``(..., n)``, under
        *any* admissible inputs (held over Euler steps or not), or ``None`` where none is known.

        Default: ``l(x) - margin_rate_bound() * time``. A system that knows more of its geometry may
        return a tighter bound (multi-vehicle systems use the cars' headings and turn rates). A
        rollout stops a trajectory whose floor over the time left is positive: no input can reach
        the failure set any more."""
        bound = self.margin_rate_bound()
        if bound is None:
            return None
        return self.failure_margin(x) - bound * time

    # ------------------------------------------------------------------ per-system defaults (hooks)
    # Built-in systems override these with the choices of the literature; a user system inherits
    # generic fallbacks derived from its declared physics.
    def view_dims(self) -> tuple[int, int]:
        """The two state dimensions that 2D views (renders, plot slices) show by default: the first two
        non-periodic dimensions (positions, typically), else the first two."""
        plain = [i for i, p in enumerate(self.periodic) if not p]
        if self.state_dim < 2:
            return (0, 0)
        return (plain[0], plain[1]) if len(plain) >= 2 else (0, 1)

    def reference_slice(self) -> tuple[int, float]:
        """``(dimension, value)`` of the 2D slice that grid comparisons report beside the whole volume:
        the nodes of that dimension nearest that value. Default: the last dimension at its domain centre."""
        lo, hi = self.domain[-1]
        return (self.state_dim - 1, 0.5 * (lo + hi))

    def plot_slices(self) -> list[tuple[tuple[float, ...], tuple[int, int], str]]:
        """``(base state, (i, j), title)`` of the 2D slices that plots draw by default: the domain
        centre over :meth:`view_dims`."""
        centre = tuple(0.5 * (lo + hi) for lo, hi in self.domain)
        return [(centre, self.view_dims(), "domain centre")]

    def margin_rate_estimate(self, samples: int = 4096, seed: int = 0) -> float:
        """The largest ``|d l(x(t)) / dt|`` over ``samples`` states drawn from the domain and every
        admissible input (exact over the input boxes: ``grad l . xdot`` is affine in the inputs).

        A sampled estimate, not a bound: it sets default filter thresholds for systems that declare
        no :meth:`margin_rate_bound`, and never licenses skipping simulation."""
        x = self.sample_states(samples, torch.Generator().manual_seed(seed), dtype=torch.float64).requires_grad_(True)
        (p,) = torch.autograd.grad(self.boundary_value(x).sum(), x)  # l, or max(l, -g): what V starts from
        x = x.detach()
        cols, pc = TORCH.unbind(x), TORCH.unbind(p)
        centre = self.xdot_columns(cols, self.control_bounds.center, self.disturbance_bounds.center, TORCH)
        rate = sum(pi * fi for pi, fi in zip(pc, centre)).abs()
        sides = [(self.control_matrix(cols, TORCH), self.control_bounds)]
        if self.disturbance_dim:
            sides.append((self.disturbance_matrix(cols, TORCH), self.disturbance_bounds))
        for matrix, box in sides:
            switching = self._switching(matrix, pc, box.dim)
            if isinstance(box, Ball):  # max over the ball of |s . (u - c)| is r |s|_2
                if any(isinstance(sj, torch.Tensor) for sj in switching):
                    rate = rate + box.radius * TORCH.norm(switching)
                continue
            for sj, hw in zip(switching, box.half_width):
                rate = rate + hw * (sj.abs() if isinstance(sj, torch.Tensor) else abs(sj))
        rate = rate[torch.isfinite(rate)]
        return float(rate.max()) if rate.numel() else 0.0

    def parameters(self) -> dict[str, Any]:
        """Constructor arguments that rebuild this system (JSON-serialisable)."""
        return {}

    def physics_config(self) -> dict[str, Any]:
        """What the dynamics, input boxes and failure set depend on: :meth:`config` without the
        horizon and the sampling box. Two systems with equal physics can share a value function
        (e.g. a 9D network filters a 2 s merge scene of the same three cars)."""
        params = {k: v for k, v in self.parameters().items() if k not in ("horizon", "half_width")}
        return {"name": self.reference(), "parameters": params}

    def same_physics(self, other: ControlAffineSystem) -> bool:
        """The package's one compatibility rule: a value function of ``other`` may serve ``self``
        when their physics agree (:meth:`physics_config`); horizons are checked where times are used."""
        return isinstance(other, ControlAffineSystem) and self.physics_config() == other.physics_config()

    def require_same_physics(self, other: ControlAffineSystem, what: str) -> None:
        """Raise ``ValueError`` saying ``what`` is for ``other`` unless :meth:`same_physics` holds
        (naming both kinds first where the kinds of problem differ: their values mean opposite things)."""
        if isinstance(other, ControlAffineSystem) and other.kind != self.kind:
            raise ValueError(
                f"{what} is for a {other.kind} problem ({other.name}), not a {self.kind} problem ({self.name}): "
                "their values do not compare"
            )
        if not self.same_physics(other):
            found = other.config() if isinstance(other, ControlAffineSystem) else type(other).__name__
            raise ValueError(f"{what} is for system {found}, not {self.config()}")

    # ------------------------------------------------------------------ description
    @property
    def state_dim(self) -> int:
        return len(self.state_names)

    @property
    def control_dim(self) -> int:
        return self.control_bounds.dim

    @property
    def disturbance_dim(self) -> int:
        return self.disturbance_bounds.dim

    @property
    def periodic_dims(self) -> tuple[int, ...]:
        dims = self.__dict__.get("_periodic_dims")
        if dims is None:
            dims = self.__dict__["_periodic_dims"] = tuple(i for i, p in enumerate(self.periodic) if p)
        return dims

    def reference(self) -> str:
        """The registered name of this system's class, or else its import path ``module:ClassName``."""
        return system_reference(type(self))

    def config(self) -> dict[str, Any]:
        """``{"name": ..., "parameters": {...}}``: enough to rebuild the system and compare two."""
        return {"name": self.reference(), "parameters": self.parameters()}

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ControlAffineSystem) and self.config() == other.config()

    def __hash__(self) -> int:
        return hash(json.dumps(self.config(), sort_keys=True))

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in self.parameters().items())
        return f"{type(self).__name__}({params})"

    def validate(self) -> None:
        """Check the declared attributes and probe the physics on a few states; ``ValueError`` naming
        the field otherwise. Runs after every constructor (a user system need not call it)."""
        what = f"{type(self).__name__}"
        for attr in ("state_names", "domain", "periodic", "control_bounds", "horizon"):
            if not hasattr(self, attr):
                raise ValueError(f"{what}: declare {attr!r} (see ControlAffineSystem)")
        n = len(self.state_names)
        if n == 0 or len(self.domain) != n or len(self.periodic) != n:
            raise ValueError(
                f"{what}: state_names ({n}), domain ({len(self.domain)}) and periodic "
                f"({len(self.periodic)}) must have the same nonzero length"
            )
        if len(set(self.state_names)) != n:
            raise ValueError(f"{what}: state_names must be distinct, got {self.state_names}")
        for name, bounds in zip(self.state_names, self.domain):
            lo, hi = bounds if len(bounds) == 2 else (math.nan, math.nan)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"{what}: domain of {name} must be finite with low < high, got {bounds}")
        for name, periodic, (lo, hi) in zip(self.state_names, self.periodic, self.domain):
            if periodic and not (abs(lo + math.pi) < 1e-6 and abs(hi - math.pi) < 1e-6):
                raise ValueError(f"{what}: periodic dimension {name} must span [-pi, pi), got [{lo}, {hi}]")
        for side in ("control_bounds", "disturbance_bounds"):
            if not isinstance(getattr(self, side), (Box, Ball)):
                raise ValueError(f"{what}: {side} must be a Box or a Ball, got {getattr(self, side)!r}")
        problem = problem_kind(self.kind, what)
        for attr in ("control_objective", "disturbance_objective"):
            if any(attr in vars(cls) for cls in type(self).__mro__ if cls is not ControlAffineSystem):
                raise ValueError(
                    f"{what}: declare kind = 'avoid', 'reach' or 'reach-avoid' instead of {attr}: the "
                    "players' objectives follow from the kind"
                )
        needed = ["failure_margin_columns"] if problem.name == "avoid" else ["target_margin_columns"]
        needed += ["constraint_margin_columns"] if problem.has_constraint else []
        for method in needed:
            if getattr(type(self), method) is getattr(ControlAffineSystem, method):
                raise ValueError(f"{what}: a {problem.name} system must define {method}")
        positive_finite(f"{what}: horizon", self.horizon)
        self._probe_physics(what)

    def _probe_physics(self, what: str) -> None:
        """Evaluate the physics on 4 states of the domain: column counts, matrix indices, ``l``'s shape."""
        x = TORCH.unbind(self.sample_states(4, torch.Generator().manual_seed(0), dtype=torch.float64))
        n = self.state_dim
        drift = self.drift(x, TORCH)
        if len(drift) != n:
            raise ValueError(f"{what}: drift returned {len(drift)} columns, expected {n} (one per state)")
        for side, matrix, m in (
            ("control_matrix", self.control_matrix(x, TORCH), self.control_dim),
            ("disturbance_matrix", self.disturbance_matrix(x, TORCH), self.disturbance_dim),
        ):
            for key in matrix:
                if not (isinstance(key, tuple) and len(key) == 2 and 0 <= key[0] < n and 0 <= key[1] < m):
                    raise ValueError(
                        f"{what}: {side} entry {key!r} is out of range: keys are (state index < {n}, input index < {m})"
                    )
        methods = [self.problem.margin_method] + (["constraint_margin_columns"] if self.problem.has_constraint else [])
        for method in methods:
            margin = getattr(self, method)(x, TORCH)
            if not isinstance(margin, torch.Tensor) or tuple(margin.shape) != (4,):
                shape = tuple(margin.shape) if isinstance(margin, torch.Tensor) else type(margin).__name__
                raise ValueError(
                    f"{what}: {method} must return one value per state, shape (4,) for 4 states, got {shape}"
                )
            if not torch.isfinite(margin).all():
                raise ValueError(f"{what}: {method} returned non-finite values inside the domain")

    # ------------------------------------------------------------------ derived, on columns
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

    # ------------------------------------------------------------------ derived, batched torch
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
