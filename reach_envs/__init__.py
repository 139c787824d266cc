"""reach_envs: scenes and Gymnasium / PettingZoo environments for the systems of :mod:`reach.systems`.

Importing the package registers ``Air3D-v0``, ``MultiVehicle6D-v0`` and ``MultiVehicle9D-v0`` (named
scenes), ``DubinsReachAvoid-v0`` (the built-in reach-avoid car, :data:`SYSTEM_ENVS`) and ``Reach-v0``
(any system: ``gym.make("Reach-v0", system=DubinsAvoid(), dt=0.02)``, or ``system="dubins3d"`` for
DeepReach's reach problem) with Gymnasium (also reachable as ``gym.make("reach_envs:Air3D-v0")``).
Environments of reach and reach-avoid systems end on reaching the goal or on a collision, and report
which in ``info["outcome"]`` (:mod:`reach_envs.env`). Registration is by entry-point
string, so importing this package loads no environment module until an env is made.

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

#: Gymnasium id -> the system and scene fields of a built-in system's env. Not named scenes: every id
#: of :data:`ENV_SCENES` ships a value network for safety filters, which handle avoid problems only.
SYSTEM_ENVS: dict[str, dict[str, Any]] = {
    "DubinsReachAvoid-v0": {"system": "dubinsreachavoid", "disturbance": "pursue"},
}

#: Gymnasium id of the environment of any system, given as ``system=``.
SYSTEM_ENV_ID = "Reach-v0"


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

__all__ = ["ENV_SCENES", "SYSTEM_ENVS", "SYSTEM_ENV_ID", "make_env", "make_vector_env"]
