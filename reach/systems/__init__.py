"""Dynamical systems: one definition each, from which envs, solvers, training and safety derive.

``make_system("air3d")``, ``make_system("my_pkg.dynamics:DubinsAvoid")`` or
``system_from_config(system.config())`` build a system by registered name or import path;
``@register_system`` adds a user's class to the registry (see :mod:`reach.systems.registry`).
"""

from __future__ import annotations

from reach.systems.air3d import Air3D, RelativePair
from reach.systems.arrays import FLOAT, NUMPY, TORCH
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Ball, Box
from reach.systems.deepreach_catalogue import (
    NarrowPassage,
    ParameterizedVertDrone2D,
    Quadrotor,
    ReachAvoidRocketLanding,
    RocketLanding,
)
from reach.systems.deepreach_normalisation import DeepReachNormalisation
from reach.systems.dubins import Dubins3D, DubinsReachAvoid
from reach.systems.multivehicle import (
    Car,
    MultiVehicle,
    MultiVehicle6D,
    MultiVehicle9D,
    MultiVehicle12D,
    MultiVehicle15D,
)
from reach.systems.registry import (
    SYSTEMS,
    make_system,
    register_system,
    system_class,
    system_from_config,
    trust_module,
)
from reach.value_function import ValueFunction

for _builtin in (
    Air3D,
    RelativePair,
    MultiVehicle,
    MultiVehicle6D,
    MultiVehicle9D,
    MultiVehicle12D,
    MultiVehicle15D,
    Dubins3D,
    DubinsReachAvoid,
    NarrowPassage,
    Quadrotor,
    ParameterizedVertDrone2D,
    RocketLanding,
    ReachAvoidRocketLanding,
):
    register_system(_builtin)


__all__ = [
    "FLOAT",
    "NUMPY",
    "SYSTEMS",
    "TORCH",
    "Air3D",
    "Ball",
    "Box",
    "Car",
    "ControlAffineSystem",
    "DeepReachNormalisation",
    "Dubins3D",
    "DubinsReachAvoid",
    "MultiVehicle",
    "MultiVehicle6D",
    "MultiVehicle9D",
    "MultiVehicle12D",
    "MultiVehicle15D",
    "NarrowPassage",
    "ParameterizedVertDrone2D",
    "Quadrotor",
    "ReachAvoidRocketLanding",
    "RelativePair",
    "RocketLanding",
    "ValueFunction",
    "make_system",
    "register_system",
    "system_class",
    "system_from_config",
    "trust_module",
]
