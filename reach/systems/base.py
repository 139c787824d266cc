"""The one place where a dynamical system is defined, and everything derived from it.

A concrete system declares only physics (see :class:`ControlAffineSystem`): its state layout, the
control-affine dynamics ``x' = f(x) + G_u(x) u + G_d(x) d`` with box-bounded inputs, which player
maximises the value, the failure margin ``l(x)`` and a default horizon. Everything the rest of the
library needs is derived once, generically, in the classes :class:`ControlAffineSystem` inherits,
one module per job:

* :mod:`reach.systems.optimal_inputs`: the Hamiltonian ``H(x, p) = opt_u opt_d p . (f + G_u u + G_d d)``,
  the optimal control and disturbance (extreme points of the input boxes), and the per-dimension
  bound on ``|dH/dp_i|`` used as Lax-Friedrichs dissipation by the grid solver;
* :mod:`reach.systems.batched`: batched dynamics, margins, heading wrapping and sampling on tensors;
* :mod:`reach.systems.margins`: bounds and estimates of how fast the failure margin can change;
* :mod:`reach.systems.limits`: state limits the inputs respect, which the discrete step keeps.

This module keeps the declarations, the kind of problem, the per-system defaults, the identity
(configuration, equality, physics compatibility) and the checks run on construction.

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
from collections.abc import Sequence
from typing import Any, ClassVar

import torch

from reach.systems.arrays import TORCH, Backend, Column, InputMatrix
from reach.systems.batched import BatchedPhysics
from reach.systems.box import NO_INPUT, Ball, Box, InputSet
from reach.systems.class_names import system_reference
from reach.systems.deepreach_normalisation import DeepReachNormalisation
from reach.systems.limits import StateLimits
from reach.systems.margins import MarginBounds
from reach.systems.optimal_inputs import OptimalInputs
from reach.systems.problem import Objective, ProblemKind, check_margins, problem_kind
from reach.validation import positive_finite


class _CheckedOnConstruction(ABCMeta):
    """Runs :meth:`ControlAffineSystem.validate` after every constructor: a bad definition fails when
    it is built, naming the field, not later inside a solver or a training step."""

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        system = super().__call__(*args, **kwargs)
        system.validate()
        return system


class ControlAffineSystem(OptimalInputs, BatchedPhysics, MarginBounds, StateLimits, metaclass=_CheckedOnConstruction):
    """Base class of every dynamical system; subclasses declare physics only.

    Subclasses set the class or instance attributes below and implement :meth:`drift`,
    :meth:`control_matrix`, optionally :meth:`disturbance_matrix`, and :meth:`failure_margin_columns`.
    Every instance is checked by :meth:`validate` when it is constructed. What is derived from the
    physics comes from the classes it inherits: :class:`~reach.systems.optimal_inputs.OptimalInputs`
    (Hamiltonian, optimal inputs, dissipation), :class:`~reach.systems.batched.BatchedPhysics` (the
    batched tensor interface), :class:`~reach.systems.margins.MarginBounds` (how fast the margin
    can change) and :class:`~reach.systems.limits.StateLimits` (state limits the inputs respect).
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

    def training_domain(self) -> tuple[tuple[float, float], ...]:
        """The box a value network's training draws its states from: :attr:`domain` (the box the
        network is asked about), widened where trajectories from it leave it before their margin
        decides them. A state's value comes from where its trajectory goes; across a face that the
        trajectories leave through, a residual drawn only inside the box does not determine the value,
        and a network fills it in as it likes. Default: :attr:`domain`."""
        return self.domain

    def value_scale(self) -> float:
        """How far, in the margin's units, ``V(x, horizon)`` may lie from ``l(x)``: the output scale a
        value network starts from (``V = l + (t / T) value_scale o`` in the exact parameterisation).
        A sine network's output ``o`` starts near zero and Adam moves each weight by about the
        learning rate a step, so a value that falls many units below ``l`` within the horizon stays
        out of a run's reach unless the scale carries it. Default 1.0."""
        return 1.0

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

    # ------------------------------------------------------------------ identity
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
        problem_kind(self.kind, what)  # an unknown kind, refused by name
        for attr in ("control_objective", "disturbance_objective"):
            if any(attr in vars(cls) for cls in type(self).__mro__ if cls is not ControlAffineSystem):
                raise ValueError(
                    f"{what}: declare kind = 'avoid', 'reach' or 'reach-avoid' instead of {attr}: the "
                    "players' objectives follow from the kind"
                )
        positive_finite(f"{what}: horizon", self.horizon)
        self.check_state_limits(what)
        self._probe_physics(what)

    def _probe_physics(self, what: str) -> None:
        """Evaluate the physics on 4 states of the domain: column counts, matrix indices, and the margins
        against the kind (:func:`~reach.systems.problem.check_margins`)."""
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
        check_margins(self, x, what)  # the kind's margins, and no other: real, finite, one per state
