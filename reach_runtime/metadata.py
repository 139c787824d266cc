"""What an exported filter declares about itself: its ``reach.*`` metadata, decoded and checked.

Each fact is stored once: the threshold is the settings' (``reach.settings``, the value the graph
was traced with), the problem kind is ``reach.problem``. The file's digest
(:mod:`reach_runtime.digest`) covers every entry, so none can be edited apart from the graph; the
input widths are also read from the graph itself and must agree (:mod:`reach_runtime.load_checks`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

__all__ = ["FORMAT", "PROBLEMS", "TIME_TOLERANCE", "FilterMetadata", "check_format"]

#: the exported format this runtime reads (``reach.format`` in the file's metadata)
FORMAT = "reach-filter/1"

#: the problem kinds an exported filter may declare (``reach.problem``): avoid, and the reach kinds
PROBLEMS = ("avoid", "reach", "reach-avoid")

#: relative slack on the time-to-go range: times summed in float32 (``k * dt``) may overshoot it
TIME_TOLERANCE = 1e-6

#: the keys every exported filter's metadata holds
_NEEDED = (
    "system_name", "system", "problem", "state_dim", "control_dim", "domain", "control_set", "settings",
    "dt", "integrator", "time_range", "default_time_to_go", "source", "fingerprint", "source_verdict", "wrapped_dims",
)  # fmt: skip


@dataclass(frozen=True)
class FilterMetadata:
    """What an exported filter declares about itself (``reach.*`` metadata, JSON-decoded).

    ``source_verdict`` is whether the source passed its trust bar when it was exported:
    ``{"passes": True/False, "line": ...}`` for a shipped model (``pretrained:NAME``, its model
    card's verdict), ``{"passes": None, "line": ...}`` for the user's own value function."""

    system_name: str
    system: dict[str, Any]
    problem: str
    state_dim: int
    control_dim: int
    domain: tuple[tuple[float, float], ...]
    wrapped_dims: tuple[int, ...]
    control_set: dict[str, Any]
    kind: str
    settings: dict[str, Any]
    threshold: float
    dt: float | None
    integrator: str
    time_range: tuple[float, float]
    default_time_to_go: float | None
    source: str
    fingerprint: str
    source_verdict: dict[str, Any]
    raw: dict[str, Any]

    @classmethod
    def from_properties(cls, props: dict[str, str], where: str) -> FilterMetadata:
        """Decode and check the ``reach.*`` properties; ``ValueError`` naming a missing or bad one."""
        raw: dict[str, Any] = {}
        for key, text in props.items():
            if key.startswith("reach."):
                try:
                    raw[key[len("reach.") :]] = json.loads(text)
                except json.JSONDecodeError as error:
                    raise ValueError(f"{where}: metadata {key} is not JSON ({error})") from None
        check_format(props, where)
        missing = [k for k in _NEEDED if k not in raw]
        if missing:
            raise ValueError(f"{where}: metadata lacks {', '.join('reach.' + k for k in missing)}")
        try:
            meta = cls._decoded(raw)
        except (KeyError, TypeError, ValueError, OverflowError) as error:
            raise ValueError(f"{where}: malformed metadata ({type(error).__name__}: {error})") from None
        meta._check(where)
        return meta

    @classmethod
    def _decoded(cls, raw: dict[str, Any]) -> FilterMetadata:
        low, high = (float(v) for v in raw["time_range"])
        settings = dict(raw["settings"])
        verdict = dict(raw["source_verdict"])
        return cls(
            system_name=str(raw["system_name"]),
            system=dict(raw["system"]),
            problem=str(raw["problem"]),
            state_dim=_count(raw["state_dim"]),
            control_dim=_count(raw["control_dim"]),
            domain=tuple((float(a), float(b)) for a, b in raw["domain"]),
            wrapped_dims=tuple(int(d) for d in raw["wrapped_dims"]),
            control_set=dict(raw["control_set"]),
            kind=str(settings["kind"]),
            settings=settings,
            threshold=float(settings["threshold"]),
            dt=None if raw["dt"] is None else float(raw["dt"]),
            integrator=str(raw["integrator"]),
            time_range=(low, high),
            default_time_to_go=None if raw["default_time_to_go"] is None else float(raw["default_time_to_go"]),
            source=str(raw["source"]),
            fingerprint=str(raw["fingerprint"]),
            source_verdict={"passes": verdict["passes"], "line": str(verdict["line"])},
            raw=raw,
        )

    def _check(self, where: str) -> None:
        """Refuse values no export writes: naming the entry."""
        low, high = self.time_range
        if not (math.isfinite(low) and math.isfinite(high) and 0 <= low <= high):
            raise ValueError(f"{where}: metadata reach.time_range {[low, high]} is not a finite [low, high] >= 0")
        default = self.default_time_to_go
        first, last = self.accepted_times()
        if default is not None and not (math.isfinite(default) and first <= default <= last):
            raise ValueError(
                f"{where}: metadata reach.default_time_to_go {default} lies outside reach.time_range "
                f"[{low:g}, {high:g}]"
            )
        if self.problem not in PROBLEMS:
            raise ValueError(f"{where}: metadata reach.problem must be one of {PROBLEMS}, got {self.problem!r}")
        if not math.isfinite(self.threshold):
            raise ValueError(f"{where}: metadata reach.settings threshold {self.threshold} is not finite")
        if len(self.domain) != self.state_dim:
            raise ValueError(f"{where}: metadata reach.domain has {len(self.domain)} rows for {self.state_dim} states")
        if any(not 0 <= d < self.state_dim for d in self.wrapped_dims):
            raise ValueError(f"{where}: metadata reach.wrapped_dims {list(self.wrapped_dims)} names no state dimension")
        if self.source_verdict["passes"] not in (True, False, None):
            raise ValueError(f"{where}: metadata reach.source_verdict passes must be true, false or null")

    @property
    def reaches(self) -> bool:
        """Whether ``V <= 0`` is the good side (reach kinds), as the problem kind says."""
        return self.problem != "avoid"

    def accepted_times(self) -> tuple[float, float]:
        """The times-to-go a call may give: :attr:`time_range` widened by the float32 slack
        (:data:`TIME_TOLERANCE`, relative)."""
        low, high = self.time_range
        tol = TIME_TOLERANCE * max(1.0, abs(high))
        return low - tol, high + tol


def check_format(props: dict[str, str], where: str) -> None:
    """Refuse a file whose ``reach.format`` is not :data:`FORMAT` (not an exported reach filter)."""
    text = props.get("reach.format")
    try:
        found = None if text is None else json.loads(text)
    except json.JSONDecodeError:
        found = text
    if found != FORMAT:
        raise ValueError(
            f"{where}: not a reach filter of format {FORMAT!r} (reach.format = {found!r}); "
            "export it with `reach export`"
        )


def _count(value: Any) -> int:
    """A positive integer from JSON (not a bool, not a float)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{value!r} is not a positive integer")
    return value
