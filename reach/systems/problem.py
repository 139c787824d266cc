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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

Objective = Literal["max", "min"]

#: the kinds of problem a system may declare (``kind = ...``)
KINDS = ("avoid", "reach", "reach-avoid")


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


__all__ = ["KINDS", "PROBLEMS", "Objective", "ProblemKind", "problem_kind"]
