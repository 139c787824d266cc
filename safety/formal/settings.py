"""What a formal proof is asked and what it found: :class:`CertifySettings` (the level, the step, how
hard the verifier tries, the escape set and the closure's knobs), :class:`CertificationResult` (the
verifier's boxes, each with its status), and what the settings mean for a system: the escape set's
rule (:func:`escape_rule`) and the box a closure runs over (:func:`closure_domain`).

The verifier (:mod:`safety.formal.verifier`), the closure (:mod:`safety.formal.closure`), the
certificate file (:mod:`safety.formal.certificate`) and its checker (:mod:`safety.formal.checker`)
all read these; the module docstring of :mod:`safety.formal.verifier` says what a proof claims.
"""

from __future__ import annotations

import inspect
import math
from dataclasses import asdict, dataclass, field

import torch

from reach.integrators import check_integrator
from reach.systems import ControlAffineSystem
from reach.validation import positive_finite

__all__ = [
    "ESCAPE",
    "OUTSIDE",
    "PROVEN",
    "REFUTED",
    "STATUS_NAMES",
    "UNKNOWN",
    "CertificationResult",
    "CertifySettings",
    "certify_defaults",
    "closure_domain",
    "derived_defaults",
    "escape_rule",
]

#: box statuses (``escape``: every state of the box is in the escape set, which needs no proof)
OUTSIDE, PROVEN, REFUTED, UNKNOWN, ESCAPE = 0, 1, 2, 3, 4
STATUS_NAMES = ("outside", "proven", "refuted", "unknown", "escape")


@dataclass(frozen=True)
class CertifySettings:
    """What a certificate proves and how hard the verifier tries (all checked at construction)."""

    level: float  # c: the set is {V(x, T) >= c}
    time_to_go: float  # T
    dt: float
    integrator: str = "euler"
    #: each disturbance dimension is split into this many pieces, each piece proven on its own
    #: (tighter bounds of the next states; the claim is the same: every disturbance)
    disturbance_splits: int = 2
    initial_splits: int = 8  # the first cover: this many boxes per dimension
    min_relative_width: float = 1 / 256  # boxes narrower than this (share of the span) are not split
    batch: int = 512  # boxes bounded at once
    max_boxes: int = 2_000_000  # stop (unfinished, never "certified") past this many boxes handled
    max_seconds: float | None = None  # ... or past this wall time
    #: m: the states with failure margin ``l(x) >= m`` form the escape set ``E``, certified by the
    #: system's own lemmas instead of the network (:func:`escape_rule`); ``None``: no escape set
    escape_margin: float | None = None
    #: boxes meeting the band below ``E`` are split down to this width (share of the span) to prove
    #: ``V >= c`` on all of them, and (b); the band is thin, so finer there costs little (``None``: as the rest)
    band_min_relative_width: float | None = None
    #: before the closure (:func:`safety.formal.closure.certified_set`), boxes wider than this (share of
    #: the span) are cut into halves down to it, each with its own backup input: a coarse proven box
    #: needs one input for all of it, which a neutral game's flow may not allow (``None``: as proven)
    closure_relative_width: float | None = None
    #: the closure (not the verifier) runs over the state box widened this many times about its
    #: centre in every non-periodic dimension (a power of two), the escape set beyond the wide box;
    #: boxes beyond the network's box are kept by where their next states land alone, never by the
    #: network. Needs ``closure_relative_width`` (the wide box is covered by cells that wide)
    closure_scale: int = 1
    #: after the closure, the boxes not kept (but not all failure) near the kept set are cut into halves
    #: along every dimension and the closure runs again, this many times: the cover grows fine only
    #: near the set's edge (each time the finest boxes halve)
    closure_refinements: int = 0
    #: "near": within this many of the box's own widths of a kept box, in every dimension
    closure_refine_reach: int = 8

    def __post_init__(self) -> None:
        if not math.isfinite(self.level):
            raise ValueError(f"level must be finite, got {self.level!r}")
        if self.escape_margin is not None:
            positive_finite("escape_margin", self.escape_margin)
        positive_finite("time_to_go", self.time_to_go)
        positive_finite("dt", self.dt)
        check_integrator(self.integrator)
        for name in ("disturbance_splits", "initial_splits", "batch", "max_boxes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.max_seconds is not None:
            positive_finite("max_seconds", self.max_seconds)
        refinements = self.closure_refinements
        if isinstance(refinements, bool) or not isinstance(refinements, int) or refinements < 0:
            raise ValueError(f"closure_refinements must be an integer >= 0, got {refinements!r}")
        reach = self.closure_refine_reach
        if isinstance(reach, bool) or not isinstance(reach, int) or reach < 1:
            raise ValueError(f"closure_refine_reach must be a positive integer, got {reach!r}")
        scale = self.closure_scale
        if isinstance(scale, bool) or not isinstance(scale, int) or scale < 1 or scale & (scale - 1):
            raise ValueError(f"closure_scale must be a power of two (1, 2, 4, ...), got {scale!r}")
        if scale > 1 and self.closure_relative_width is None:
            raise ValueError("closure_scale above 1 needs closure_relative_width: the cells of the wide box")
        for name in ("min_relative_width", "band_min_relative_width", "closure_relative_width"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, float | int) and 0 < value <= 1):
                raise ValueError(f"{name} must lie in (0, 1], got {value!r}")


@dataclass
class CertificationResult:
    """The verifier's boxes (corners ``lo``, ``hi``), each one's status and backup input index
    (``-1`` where none), the candidate inputs, and what it cost. ``certified`` only when every box
    is outside or proven and the run finished."""

    settings: CertifySettings
    lo: torch.Tensor
    hi: torch.Tensor
    status: torch.Tensor
    backup: torch.Tensor
    candidates: torch.Tensor
    counterexamples: list[dict] = field(default_factory=list)
    finished: bool = True
    wall_time: float = 0.0
    boxes_handled: int = 0

    #: boxes of the band below the escape set not proven to hold only states of ``S_c`` (they undo ``E``)
    band_open: int = 0

    @property
    def certified(self) -> bool:
        decided = (self.status == OUTSIDE) | (self.status == PROVEN) | (self.status == ESCAPE)
        return self.finished and self.band_open == 0 and bool(decided.all())

    def volume_shares(self) -> dict[str, float]:
        """Each status's share of the state box's volume."""
        volume = (self.hi - self.lo).prod(-1)
        total = float(volume.sum())
        return {name: float(volume[self.status == k].sum()) / total for k, name in enumerate(STATUS_NAMES)}

    def summary(self) -> dict:
        return {
            "certified": self.certified,
            "finished": self.finished,
            "boxes": len(self.status),
            "boxes_handled": self.boxes_handled,
            "band_open": self.band_open,
            "wall_time_s": self.wall_time,
            **{f"volume_{k}": v for k, v in self.volume_shares().items()},
            "settings": asdict(self.settings),
        }


def escape_rule(system: ControlAffineSystem, settings: CertifySettings, scale: int = 1) -> tuple[float, float] | None:
    """``(m, delta)`` of the escape set ``E = {x : l(x) >= m}``, or ``None`` where the settings ask for
    none. Sound when (the system's declared lemmas) every state outside the domain has ``l >= m``
    (:meth:`~reach.systems.base.ControlAffineSystem.margin_outside_domain`) and one step lowers ``l``
    by at most ``delta`` from any state (:meth:`~reach.systems.base.ControlAffineSystem.margin_step_bound`):
    then a next state that leaves the domain is in ``E``, and a step from ``E`` lands in ``E`` or in
    the band ``m - delta <= l < m``, which lies inside the domain. ``scale``: the domain widened that
    many times (the closure's, ``closure_scale``). Refused, naming why, otherwise."""
    m = settings.escape_margin
    if m is None:
        return None
    delta = system.margin_step_bound(settings.dt, settings.integrator)
    if delta is None:
        raise ValueError(
            f"escape_margin: {system.name} declares no bound on how much one {settings.integrator} step lowers "
            "its failure margin (margin_step_bound), so it has no escape set"
        )
    if scale != 1 and "scale" not in inspect.signature(system.margin_outside_domain).parameters:
        raise ValueError(
            f"closure_scale: {system.name}'s margin_outside_domain takes no scale, so no wider box has an escape set"
        )
    least = system.margin_outside_domain() if scale == 1 else system.margin_outside_domain(scale)
    if least is None:
        raise ValueError(
            f"escape_margin: {system.name} declares no lower bound of its failure margin outside its domain "
            "(margin_outside_domain), so it has no escape set"
        )
    if m > least:
        raise ValueError(
            f"escape_margin {m:g} is above {least:g}, the least failure margin outside {system.name}'s domain"
            f"{'' if scale == 1 else f' widened {scale} times'}: "
            "a state that leaves the domain might not be in the escape set"
        )
    return m, float(delta)


#: derived defaults: the closure runs over the box this many times wider where the lemmas allow
DEFAULT_CLOSURE_SCALE = 4
#: ... on the finest power-of-two cells with at most this many over the wide box
DEFAULT_CLOSURE_CELLS = 2**21
#: ... cut finer near the set's edge this many times
DEFAULT_REFINEMENTS = 3
#: the proof fields a system's certification defaults may name
DEFAULT_FIELDS = (
    "level",
    "escape_margin",
    "closure_scale",
    "closure_relative_width",
    "min_relative_width",
    "closure_refinements",
)


def derived_defaults(system: ControlAffineSystem, dt: float, integrator: str = "euler") -> dict[str, object]:
    """Proof settings derived from ``system``'s lemmas alone (what a user's system gets):

    - the zero level;
    - where one step's loss of margin is bounded (:meth:`~reach.systems.margins.MarginBounds.margin_step_bound`
      for this ``dt`` and ``integrator``) and the margin outside the domain too
      (:meth:`~reach.systems.margins.MarginBounds.margin_outside_domain`): an escape set as far out as
      that bound allows, over the box :data:`DEFAULT_CLOSURE_SCALE` times wider where the bound takes
      a scale (else the box itself), on the finest power-of-two cells of which at most
      :data:`DEFAULT_CLOSURE_CELLS` cover the wide box, cut finer :data:`DEFAULT_REFINEMENTS` times
      near the set's edge. Without those lemmas, the dataclass's own defaults."""
    out: dict[str, object] = {"level": 0.0}
    if system.margin_step_bound(dt, integrator) is None:
        return out
    takes_scale = "scale" in inspect.signature(system.margin_outside_domain).parameters
    scale = DEFAULT_CLOSURE_SCALE if takes_scale else 1
    margin = system.margin_outside_domain(scale) if takes_scale else system.margin_outside_domain()
    if margin is None or not math.isfinite(margin) or margin <= 0:
        return out
    n = system.state_dim
    width = 2.0 ** -max(0, math.floor(math.log2(DEFAULT_CLOSURE_CELLS ** (1 / n) / scale)))
    out.update(
        escape_margin=float(margin),
        closure_scale=scale,
        closure_relative_width=width,
        min_relative_width=width,
        closure_refinements=DEFAULT_REFINEMENTS,
    )
    return out


def certify_defaults(
    system: ControlAffineSystem, dt: float, integrator: str = "euler", given: dict[str, object] | None = None
) -> dict[str, object]:
    """The proof settings ``reach certify`` uses for the fields not ``given``: the system's own
    (:meth:`~reach.systems.margins.MarginBounds.certification_defaults`), else :func:`derived_defaults`.
    A declared field outside :data:`DEFAULT_FIELDS` is refused, naming it. Where ``given`` sets the
    closure's scale but not the escape margin, the default margin follows that scale (as far out as
    :meth:`~reach.systems.margins.MarginBounds.margin_outside_domain` allows there), so that one
    option can be changed alone."""
    given = dict(given or {})
    declared = system.certification_defaults()
    if declared is None:
        defaults = derived_defaults(system, dt, integrator)
    else:
        unknown = sorted(set(declared) - set(DEFAULT_FIELDS))
        if unknown:
            raise ValueError(f"{system.name}.certification_defaults names fields no proof takes: {unknown}")
        defaults = dict(declared)
    if "closure_scale" in given and "escape_margin" not in given and defaults.get("escape_margin") is not None:
        scale = given["closure_scale"]
        takes_scale = "scale" in inspect.signature(system.margin_outside_domain).parameters
        if takes_scale:
            margin = system.margin_outside_domain(scale)
        else:  # a bound for the domain itself only
            margin = system.margin_outside_domain() if scale == 1 else None
        if margin is None or not margin > 0:
            defaults.pop("escape_margin")
        else:
            defaults["escape_margin"] = float(margin)
    return {k: v for k, v in defaults.items() if k not in given}


def closure_domain(system: ControlAffineSystem, scale: int = 1, device: str | torch.device = "cpu") -> torch.Tensor:
    """``(n, 2)`` the box a closure runs over: the system's domain widened ``scale`` times about its
    centre in every non-periodic dimension (``CertifySettings.closure_scale``)."""
    box = system.domain_tensor(torch.float64, device)
    centre = box.mean(-1, keepdim=True)
    periodic = torch.tensor([i in system.periodic_dims for i in range(system.state_dim)], device=box.device)
    return torch.where(periodic[:, None], box, centre + scale * (box - centre))
