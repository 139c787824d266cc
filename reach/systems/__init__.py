"""Dynamical systems: one definition each, from which envs, solvers, training and safety derive.

``make_system("air3d")`` or ``system_from_config(system.config())`` rebuild a system by name.
"""

from __future__ import annotations

from typing import Any

from reach.systems.air3d import Air3D, RelativePair
from reach.systems.backend import FLOAT, NUMPY, TORCH
from reach.systems.base import Box, ControlAffineSystem, DeepReachNormalisation
from reach.systems.multivehicle import Car, MultiVehicle, MultiVehicle6D, MultiVehicle9D
from reach.value_function import ValueFunction

#: Systems by registry name.
SYSTEMS: dict[str, type[ControlAffineSystem]] = {
    cls.name: cls for cls in (Air3D, RelativePair, MultiVehicle, MultiVehicle6D, MultiVehicle9D)
}


def make_system(name: str, **parameters: Any) -> ControlAffineSystem:
    """Build a system by registry name (case-insensitive), e.g. ``make_system("multivehicle9d")``."""
    key = name.lower().replace("-", "").replace("_", "")
    if key not in SYSTEMS:
        raise ValueError(f"unknown system {name!r}; known systems: {sorted(SYSTEMS)}")
    try:
        return SYSTEMS[key](**parameters)
    except TypeError as err:  # unknown or missing parameters
        raise ValueError(f"system {name!r}: bad parameters {parameters} ({err})") from None


def system_from_config(config: dict[str, Any]) -> ControlAffineSystem:
    """Inverse of :meth:`ControlAffineSystem.config`."""
    if not isinstance(config, dict) or "name" not in config:
        raise ValueError(f"a system config needs a 'name' key, got {config!r}")
    return make_system(config["name"], **config.get("parameters", {}))


__all__ = [
    "FLOAT",
    "NUMPY",
    "SYSTEMS",
    "TORCH",
    "Air3D",
    "Box",
    "Car",
    "ControlAffineSystem",
    "DeepReachNormalisation",
    "MultiVehicle",
    "MultiVehicle6D",
    "MultiVehicle9D",
    "RelativePair",
    "ValueFunction",
    "make_system",
    "system_from_config",
]
