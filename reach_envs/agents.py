"""The agents of a multi-agent system: which of its control inputs each one acts.

A system declares its agents with an optional attribute ``agent_inputs``: agent name -> indices of
the control inputs that agent acts (:class:`~reach.systems.deepreach_catalogue.NarrowPassage`:
``car_1`` acts inputs 0, 1, car 1's acceleration and steering rate, ``car_2`` inputs 2, 3). A
:class:`~reach.systems.multivehicle.MultiVehicle` (the N-car family, the named car scenes) needs no
declaration: one agent per control car, named after the car, acting its turn rate.

Every control input must be acted by exactly one agent, else ``ValueError`` names the system. The
PettingZoo environment (:mod:`reach_envs.parallel`) takes its agents from :func:`agent_inputs`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from reach.systems.base import ControlAffineSystem
from reach.systems.multivehicle import MultiVehicle


def agent_inputs(system: ControlAffineSystem) -> dict[str, tuple[int, ...]] | None:
    """``agent -> control input indices`` of a multi-agent system, or ``None`` for a system without agents.

    A :class:`MultiVehicle`'s agents are its control cars; any other system's come from its own
    ``agent_inputs`` attribute."""
    if isinstance(system, MultiVehicle):
        return {system.cars[i].name: (k,) for k, i in enumerate(system.control_cars)}
    declared = getattr(system, "agent_inputs", None)
    return None if declared is None else _checked(system, declared)


def _checked(system: ControlAffineSystem, declared: Any) -> dict[str, tuple[int, ...]]:
    """``declared`` as ``{name: tuple of ints}``, each control input acted by exactly one agent."""
    where = f"{system.name}: agent_inputs"
    if not isinstance(declared, Mapping) or not declared:
        raise ValueError(f"{where} must be a non-empty mapping of agent name -> input indices, got {declared!r}")
    out: dict[str, tuple[int, ...]] = {}
    for name, indices in declared.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"{where}: agent names must be non-empty strings, got {name!r}")
        try:
            out[name] = tuple(indices)
        except TypeError:
            raise ValueError(f"{where}: agent {name!r} must act a sequence of input indices, got {indices!r}") from None
        if not out[name] or not all(isinstance(k, int) and not isinstance(k, bool) for k in out[name]):
            raise ValueError(f"{where}: agent {name!r} must act one or more input indices (ints), got {indices!r}")
    acted = sorted(k for indices in out.values() for k in indices)
    if acted != list(range(system.control_dim)):
        raise ValueError(
            f"{where} must give each of the {system.control_dim} control inputs to exactly one agent, got {out}"
        )
    return out


__all__ = ["agent_inputs"]
