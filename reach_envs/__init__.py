"""reach_envs: scenes and Gymnasium / PettingZoo environments for the systems of :mod:`reach.systems`.

Importing the package registers with Gymnasium (also reachable as ``gym.make("reach_envs:Air3D-v0")``):

* :data:`ENV_SCENES`, named scenes that ship a pretrained value network for safety filters:
  ``Air3D-v0``, ``MultiVehicle6D-v0`` and ``MultiVehicle9D-v0``;
* :data:`SYSTEM_ENVS`, every other built-in system, no value network shipped yet:
  ``DubinsReachAvoid-v0``, ``Dubins3D-v0`` (DeepReach's reach problem), ``NarrowPassage-v0``,
  ``Quadrotor-v0``, ``ParameterizedVertDrone2D-v0``, ``MultiVehicle12D-v0``, ``MultiVehicle15D-v0``,
  ``RocketLanding-v0`` and ``ReachAvoidRocketLanding-v0`` (thrust in a disc: an action outside the
  unit disc is scaled back onto it, :func:`reach_envs.spaces.inputs_of_actions`);
* ``Reach-v0``, any system: ``gym.make("Reach-v0", system=DubinsAvoid(), dt=0.02)``;
* :data:`FLEET_ENVS`, fleets of N cars driving to goals (:mod:`reach_envs.fleet_envs`):
  ``FleetCircleSwap-v0``, ``FleetRandomGoals-v0`` and ``FleetIntersection-v0``, with a PettingZoo
  twin, :class:`reach_envs.fleet_envs.FleetParallelEnv`.

Environments of reach and reach-avoid systems end on reaching the goal or on a collision, and report
which in ``info["outcome"]`` (:mod:`reach_envs.env`). The multi-agent systems (the car scenes, the
N-car family, NarrowPassage's two cars) also have a PettingZoo env, :func:`reach_envs.parallel.parallel_env`.
Registration is by entry-point string, so importing this package loads no environment module until an
env is made.

:func:`make_env` and :func:`make_vector_env` build the environments of any system directly: an
instance, a registered name or an import path ``"pkg.mod:Class"``, with :class:`~reach_envs.scenes.Scene`
fields as keywords. Systems without cars render as a projection on two state dimensions
(:mod:`reach_envs.projection`).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

from gymnasium.envs.registration import register, registry

if TYPE_CHECKING:
    from reach_envs.env import ReachEnv
    from reach_envs.vector import ReachVectorEnv

#: Gymnasium id -> named scene it runs.
ENV_SCENES = {
    "Air3D-v0": "air3d",
    "MultiVehicle6D-v0": "pursuit-evasion-6d",
    "MultiVehicle9D-v0": "three-car-9d",
}

#: Gymnasium id -> the system (or named scene) and scene fields of a built-in system's env. Kept apart
#: from :data:`ENV_SCENES`: every id there ships a value network for safety filters, these do not (yet).
#: None of DeepReach's catalogue has a disturbance input; the quadrotor's step and initial attitudes are
#: its named scene's (``"quadrotor"``, :mod:`reach_envs.scenes`).
SYSTEM_ENVS: dict[str, dict[str, Any]] = {
    "DubinsReachAvoid-v0": {"system": "dubinsreachavoid", "disturbance": "pursue"},
    "Dubins3D-v0": {"system": "dubins3d"},
    "NarrowPassage-v0": {"system": "narrowpassage"},
    "Quadrotor-v0": {"scene": "quadrotor"},
    "ParameterizedVertDrone2D-v0": {"system": "parameterizedvertdrone2d"},
    "MultiVehicle12D-v0": {"scene": "four-car-12d"},
    "MultiVehicle15D-v0": {"scene": "five-car-15d"},
    "RocketLanding-v0": {"system": "rocketlanding", "dt": 0.01},
    "ReachAvoidRocketLanding-v0": {"system": "reachavoidrocketlanding", "dt": 0.01},
}

#: Gymnasium id of the environment of any system, given as ``system=``.
SYSTEM_ENV_ID = "Reach-v0"

#: Gymnasium id -> layout of a fleet env (:class:`reach_envs.fleet_envs.FleetEnv`): N cars, 16 by
#: default, ``gym.make("FleetCircleSwap-v0", n_cars=32)``; any :class:`~reach_envs.fleet_scenes.FleetScene`
#: field passes through.
FLEET_ENVS = {
    "FleetCircleSwap-v0": "circle-swap",
    "FleetRandomGoals-v0": "random-goals",
    "FleetIntersection-v0": "intersection",
}


def _register() -> None:
    named = {env_id: {"scene": scene} for env_id, scene in ENV_SCENES.items()}
    for env_id, kwargs in {**named, **{i: dict(f) for i, f in SYSTEM_ENVS.items()}}.items():
        if env_id in registry:
            continue
        register(
            id=env_id,
            entry_point="reach_envs.env:ReachEnv",
            vector_entry_point="reach_envs.vector:ReachVectorEnv",
            kwargs=kwargs,
        )
    if SYSTEM_ENV_ID not in registry:
        register(
            id=SYSTEM_ENV_ID,
            entry_point="reach_envs.env:ReachEnv",
            vector_entry_point="reach_envs.vector:ReachVectorEnv",
        )
    for env_id, layout in FLEET_ENVS.items():
        if env_id not in registry:
            register(id=env_id, entry_point="reach_envs.fleet_envs:FleetEnv", kwargs={"layout": layout})


def make_env(system: Any, render_mode: str | None = None, **scene_fields: Any) -> ReachEnv:
    """A Gymnasium env of any system: an instance, a registered name or an import path ``"pkg.mod:Class"``.

    ``scene_fields`` are :class:`~reach_envs.scenes.Scene` fields (``dt``, ``disturbance``,
    ``initial_state``, ``process_noise``, ``horizon``, ``view_dims``, ...); unknown ones, unknown
    systems and bad import paths raise ``ValueError`` naming them. The same env as
    ``gym.make("Reach-v0", system=system, ...)`` without Gymnasium's wrappers, with the spec
    ``gym.make`` would give it (so ``env.spec.make()`` builds another).
    """
    from reach_envs.env import ReachEnv  # lazy: importing reach_envs loads no env module

    env = ReachEnv(render_mode=render_mode, system=system, **scene_fields)
    kwargs = {"system": system, **scene_fields, **({"render_mode": render_mode} if render_mode is not None else {})}
    env.spec = dataclasses.replace(registry[SYSTEM_ENV_ID], kwargs=kwargs)
    return env


def make_vector_env(system: Any, num_envs: int, render_mode: str | None = None, **scene_fields: Any) -> ReachVectorEnv:
    """``num_envs`` copies of :func:`make_env`'s environment stepped as one NumPy batch."""
    from reach_envs.vector import ReachVectorEnv  # lazy: importing reach_envs loads no env module

    return ReachVectorEnv(num_envs, render_mode=render_mode, system=system, **scene_fields)


_register()

__all__ = ["ENV_SCENES", "FLEET_ENVS", "SYSTEM_ENVS", "SYSTEM_ENV_ID", "make_env", "make_vector_env"]
