"""The methods the fleet study compares, each as ``decide(x, u_nominal, present) -> (u, info)``.

Every filtered method reads the same pairwise value (:class:`safety.fleet.FleetValue`) over the
shipped pair grid (``pretrained:relativepair``: two cars at speed 0.6, turn rate at most 1.1, collision
radius 0.25, horizon 1 s) where the scene's cars have that physics, else over pair grids solved for
them (:func:`groundtruth.pairwise.solve_pairs`, once per process and kind). The time-to-go is the
pair problem's horizon: the filters use its value as time-invariant, as the env adapters do.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import torch

from groundtruth.pairwise import solve_pairs
from groundtruth.solution import GridSolution
from reach_envs.fleet_scenes import FleetScene
from safety.fleet import CBFSettings, DistanceCBF, FleetFilter, FleetFilterSettings, FleetValue, NaiveUnionSwitch
from studies.fleet_settings import METHODS
from training import pretrained

__all__ = ["fleet_value", "make_method"]

#: the shipped pair grid the fleet value reads where the cars match its physics
PAIR_SOURCE = "pretrained:relativepair"

Decide = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, Any]]


@functools.lru_cache(maxsize=1)
def _shipped_pair() -> GridSolution:
    """The shipped pair grid, taken only while its card's computed verdict passes (nothing picks an
    untrusted model by default)."""
    verdict = pretrained.source_verdict(PAIR_SOURCE)
    if verdict is None or not verdict.passes:
        raise ValueError(f"{PAIR_SOURCE} does not pass the trust bar ({verdict}); the fleet study will not use it")
    return GridSolution.load(pretrained.checkpoint_path(PAIR_SOURCE), outside="clamp")


def fleet_value(scene: FleetScene) -> FleetValue:
    """The pairwise value of ``scene``'s cars: over the shipped pair grid where it fits their physics,
    else over pair grids solved for them."""
    system = scene.system()
    shipped = _shipped_pair()
    try:
        return FleetValue(system, shipped)
    except ValueError:  # other speeds or turn bounds than the shipped pair's: solve their pairs
        return FleetValue(system, solve_pairs(system, progress=False))


def make_method(method: str, scene: FleetScene, **fleet_options: Any) -> Decide | None:
    """``method``'s decision rule for ``scene`` (``None`` for ``"none"``, the nominal input);
    ``fleet_options`` (``hold``, ``reaction_time``, ``tie_break``) go to the fleet filter's
    :class:`~safety.fleet.FleetFilterSettings`, whose defaults stand for those not given."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "none":
        return None
    value = fleet_value(scene)
    t = float(max(s.system.horizon for s in value.solutions))
    if method == "fleet":
        rule: Any = FleetFilter(value, FleetFilterSettings(dt=scene.dt, **fleet_options))
    elif method == "union":
        rule = NaiveUnionSwitch(value, FleetFilterSettings(dt=scene.dt))
    else:
        rule = DistanceCBF(value, CBFSettings(dt=scene.dt))

    def decide(x: torch.Tensor, u_nominal: torch.Tensor, present: torch.Tensor) -> tuple[torch.Tensor, Any]:
        return rule(x, t, u_nominal, present)

    return decide
