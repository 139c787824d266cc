"""The kind of reachability problem a system poses, declared once: which sets, who wins, what V <= 0 means.

A system names its kind (``kind = "avoid"``, the default, ``"reach"`` or ``"reach-avoid"``) and
writes only its margins; everything that depends on the kind follows from :class:`ProblemKind`:

=============  ======================================  =========  ============  ==========================
kind           margins the system writes               control    disturbance   ``V(x, t) <= 0`` means
=============  ======================================  =========  ============  ==========================
avoid          ``l``: failure margin (< 0 in failure)  maximises  minimises     failure cannot be avoided
                                                                                within ``t`` (the BRT)
reach          ``l``: target margin (< 0 in target)    minimises  maximises     the target can be reached
                                                                                within ``t``
reach-avoid    ``l``: target margin, and ``g``:        minimises  maximises     the target can be reached
               constraint margin (> 0 where allowed)                            within ``t`` while ``g``
                                                                                stays positive
=============  ======================================  =========  ============  ==========================

Every kind is a tube (reached at *some* time within ``t``), the value obeying a variational
inequality that the grid solver applies after each time step: ``V <- min(V, l)`` for avoid and
reach, and ``V <- max(min(V, l), -g)`` for reach-avoid (Fisac et al., 2015), from the boundary
value ``V(x, 0) = l(x)``, or ``max(l(x), -g(x))`` for reach-avoid. The time-to-go ``t`` counts down
to 0: ``V(x, t)`` speaks of the next ``t`` seconds.

A system writes exactly its kind's margins. One the kind has no use for would be silently ignored
(an obstacle dropped from a reach problem, a target from an avoid one), so :func:`check_margins`
refuses it when the system is constructed, naming the kind and the margin:

=============  ================================  =================================================
kind           must write                        must not write
=============  ================================  =================================================
avoid          ``failure_margin_columns``        ``target_margin_columns``,
                                                 ``constraint_margin_columns``
reach          ``target_margin_columns``         ``failure_margin_columns``,
                                                 ``constraint_margin_columns``
reach-avoid    ``target_margin_columns``,        a ``failure_margin_columns`` other than the
               ``constraint_margin_columns``     constraint margin (the failure set is where ``g``
                                                 fails; the default returns ``g``)
=============  ================================  =================================================

A margin is *written* when calling it returns values; the base class's methods raise
``NotImplementedError``, and a system whose kind is chosen per instance (``set_mode``) returns to
them with ``super()`` for the margins its kind lacks. Each written margin must return one real
floating value per state, finite at the domain states it is probed at.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch

from reach.systems.arrays import TORCH

Objective = Literal["max", "min"]

#: the kinds of problem a system may declare (``kind = ...``)
KINDS = ("avoid", "reach", "reach-avoid")

#: every margin a system may write: the failure margin (avoid), the target margin (reach kinds) and
#: the constraint margin (reach-avoid)
MARGIN_METHODS = ("failure_margin_columns", "target_margin_columns", "constraint_margin_columns")


@dataclass(frozen=True)
class ProblemKind:
    """What a kind of problem fixes: the players' objectives, which margins exist, and the meaning
    of the sublevel set ``{V <= 0}``."""

    name: str
    #: whether the control maximises ``V`` (avoid: stay out of failure) or minimises it (reach)
    control_objective: Objective
    disturbance_objective: Objective
    #: the method the system writes for ``l`` (the terminal margin of the variational inequality)
    margin_method: str
    #: whether the system also writes ``g`` (:meth:`constraint_margin_columns`), reach-avoid only
    has_constraint: bool
    #: what ``V(x, t) <= 0`` says of a state, in words
    sublevel_meaning: str

    @property
    def margin_methods(self) -> tuple[str, ...]:
        """The margins a system of this kind must write: ``l``'s method, and ``g``'s for reach-avoid."""
        return (self.margin_method, "constraint_margin_columns") if self.has_constraint else (self.margin_method,)

    @property
    def foreign_margins(self) -> tuple[str, ...]:
        """The margins this kind has no use for (see the module's table): a system must not write them,
        save a reach-avoid system's failure margin where it is the constraint margin."""
        return tuple(m for m in MARGIN_METHODS if m not in self.margin_methods)

    @property
    def reaches(self) -> bool:
        """Whether ``{V <= 0}`` is the *good* side (reach kinds), not the unsafe one (avoid)."""
        return self.name != "avoid"

    @property
    def claim(self) -> str:
        """What a value function claims of the states on its good side: ``"safe"`` (avoid: ``V > 0``)
        or ``"reachable"`` (reach kinds: ``V < 0``)."""
        return "reachable" if self.reaches else "safe"

    def orient(self, v: torch.Tensor) -> torch.Tensor:
        """``V`` turned so that ``> 0`` is the claim (:attr:`claim`): ``V`` for avoid, ``-V`` for reach
        kinds. Verification tests claims on this side: a certified level ``delta`` means the set
        ``{V > delta}`` (avoid) or ``{V < -delta}`` (reach kinds)."""
        return -v if self.reaches else v

    def boundary_value(self, margin: torch.Tensor, g: torch.Tensor | None) -> torch.Tensor:
        """``V(x, 0)``: the terminal margin ``l``, or ``max(l, -g)`` where a constraint must hold."""
        return margin if g is None else torch.maximum(margin, -g)

    def enforce(self, v: torch.Tensor, floor: torch.Tensor | None, g: torch.Tensor | None) -> torch.Tensor:
        """The variational inequality after a time step: ``min(v, floor)`` (``floor`` is ``l`` for a
        tube, the previous value for the MATLAB toolbox's ``minVOverTime``, None for a set), then
        ``max(., -g)`` where a constraint must hold."""
        if floor is not None:
            v = torch.minimum(v, floor)
        return v if g is None else torch.maximum(v, -g)


PROBLEMS: dict[str, ProblemKind] = {
    "avoid": ProblemKind(
        "avoid", "max", "min", "failure_margin_columns", False, "failure cannot be avoided within the time-to-go"
    ),
    "reach": ProblemKind(
        "reach", "min", "max", "target_margin_columns", False, "the target can be reached within the time-to-go"
    ),
    "reach-avoid": ProblemKind(
        "reach-avoid",
        "min",
        "max",
        "target_margin_columns",
        True,
        "the target can be reached within the time-to-go while the constraint margin stays positive",
    ),
}


def problem_kind(name: object, what: str = "system") -> ProblemKind:
    """The :class:`ProblemKind` called ``name``; anything else raises ``ValueError`` naming it."""
    problem = PROBLEMS.get(name) if isinstance(name, str) else None
    if problem is None:
        raise ValueError(f"{what}: kind must be one of {KINDS}, got {name!r}")
    return problem


def _article(word: str) -> str:
    return f"an {word}" if word[0] in "aeiou" else f"a {word}"


#: why a kind refuses each margin it has no use for, and what to write instead
_FOREIGN = {
    "failure_margin_columns": "a reach problem has no failure set, so it would be ignored; declare kind = 'avoid', "
    "or kind = 'reach-avoid' with the set to stay in as constraint_margin_columns",
    "target_margin_columns": "an avoid problem has no target, so it would be ignored; declare kind = 'reach' or "
    "'reach-avoid' to reach it, or remove it",
    "constraint_margin_columns": "{article} problem has no constraint, so the obstacle would be ignored; declare "
    "kind = 'reach-avoid' to keep out of it ('avoid': write it as failure_margin_columns), or remove it",
}


def check_margins(system: Any, x: Sequence[torch.Tensor], what: str) -> None:
    """Refuse, naming the kind and the margin, a system whose margins contradict its kind (the module's
    table), and any margin that does not return one real floating, finite value per state of ``x``
    (torch columns of a few domain states) - naming the state and the system's parameters where it
    is not finite. Run on construction by :meth:`~reach.systems.base.ControlAffineSystem.validate`."""
    problem = system.problem
    n = int(x[0].shape[0])
    values = {method: _margin(system, method, x, n, what) for method in problem.margin_methods}
    for method in problem.foreign_margins:
        try:
            value = getattr(system, method)(x, TORCH)
        except NotImplementedError:
            continue  # the base class's method: not written
        constraint = values.get("constraint_margin_columns")
        if constraint is not None and isinstance(value, torch.Tensor) and torch.equal(value, constraint):
            continue  # a reach-avoid failure margin that is the constraint margin, as the default is
        kind = problem.name
        if method == "failure_margin_columns" and problem.has_constraint:
            why = "a reach-avoid system's failure set is where its constraint fails: it must return "
            why += "constraint_margin_columns' values, or be left out (the default returns them)"
        else:
            why = _FOREIGN[method].format(article=_article(kind))
        raise ValueError(f"{what}: kind = {kind!r} but {method} is written: {why}")


def _margin(system: Any, method: str, x: Sequence[torch.Tensor], n: int, what: str) -> torch.Tensor:
    """One margin the kind needs at the states ``x``, checked: written, one real float per state, finite."""
    problem = system.problem
    try:
        margin = getattr(system, method)(x, TORCH)
    except NotImplementedError:
        raise ValueError(f"{what}: {_article(problem.name)} system must define {method}") from None
    if not isinstance(margin, torch.Tensor) or tuple(margin.shape) != (n,):
        shape = tuple(margin.shape) if isinstance(margin, torch.Tensor) else type(margin).__name__
        raise ValueError(f"{what}: {method} must return one value per state, shape ({n},) for {n} states, got {shape}")
    if not margin.dtype.is_floating_point:
        raise ValueError(
            f"{what}: {method} must return real floating values (a signed distance), got a {margin.dtype} tensor; "
            "a set's indicator has no distance for the value function to start from"
        )
    require_finite_margin(system, method, margin, x, what)
    return margin


def require_finite_margin(
    system: Any, method: str, margin: torch.Tensor, x: Sequence[torch.Tensor], what: str | None = None
) -> None:
    """Refuse a margin with a NaN or infinite value at the states ``x`` (columns broadcasting with
    ``margin``: the probe's states, a grid's nodes), naming the margin, the first such state and the
    system's parameters: a NaN margin reads as "not in the set" (``NaN <= 0`` is False) and poisons
    every value computed from it."""
    finite = torch.isfinite(margin)
    if bool(finite.all()):
        return
    index = tuple(int(i) for i in (~finite).nonzero()[0])
    state = [float(torch.as_tensor(c).broadcast_to(margin.shape)[index]) for c in x]
    found = "NaN" if bool(torch.isnan(margin[index])) else "inf"
    raise ValueError(
        f"{what or type(system).__name__}: {method} returned {found} at the state {state}, with parameters "
        f"{_parameters(system)}; check the parameters it uses"
    )


def _parameters(system: Any) -> str:
    """The system's parameters in words, naming its non-finite numbers (a NaN radius, say)."""
    params = dict(system.parameters())
    for key, value in vars(system).items():  # a user system may keep numbers it does not list
        if not key.startswith("_") and isinstance(value, float) and key not in params:
            params[key] = value

    def finite(value: Any) -> bool:
        if isinstance(value, (list, tuple)):
            return all(finite(v) for v in value)
        return not isinstance(value, float) or math.isfinite(value)

    bad = sorted(k for k, v in params.items() if not finite(v))
    text = "{" + ", ".join(f"{k}={v!r}" for k, v in params.items()) + "}"
    return f"{text} (not finite: {', '.join(bad)})" if bad else text


__all__ = [
    "KINDS",
    "MARGIN_METHODS",
    "PROBLEMS",
    "Objective",
    "ProblemKind",
    "check_margins",
    "problem_kind",
    "require_finite_margin",
]
