"""Safety filters for fleets of tens of Dubins cars, composed from pairwise HJ values.

* :class:`FleetValue` - the pairwise value of a fleet, evaluated only on the pairs near enough to
  matter (:mod:`safety.fleet.value`);
* :class:`FleetFilter` with :class:`FleetFilterSettings` - every threatened pair answered at once:
  the switch rule for a lone pair, one sparse QP for all larger conflicts of a batch, a counted
  fallback where a conflict is infeasible (:mod:`safety.fleet.filter`);
* :class:`DistanceCBF` and :class:`NaiveUnionSwitch` - the baselines, with the same interface
  (:mod:`safety.fleet.baselines`).
"""

from __future__ import annotations

from safety.fleet.baselines import CBFSettings, DistanceCBF, NaiveUnionSwitch
from safety.fleet.filter import FleetFilter, FleetFilterSettings, FleetInfo
from safety.fleet.value import FleetValue, PairCandidates

__all__ = [
    "CBFSettings",
    "DistanceCBF",
    "FleetFilter",
    "FleetFilterSettings",
    "FleetInfo",
    "FleetValue",
    "NaiveUnionSwitch",
    "PairCandidates",
]
