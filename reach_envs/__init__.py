"""reach_envs: scenes and Gymnasium / PettingZoo environments for the systems of :mod:`reach.systems`.

Importing the package registers ``Air3D-v0``, ``MultiVehicle6D-v0`` and ``MultiVehicle9D-v0`` with
Gymnasium (also reachable as ``gym.make("reach_envs:Air3D-v0")``). Registration is by entry-point
string, so importing this package loads no environment module until an env is made.
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

#: Gymnasium id -> named scene it runs.
ENV_SCENES = {
    "Air3D-v0": "air3d",
    "MultiVehicle6D-v0": "pursuit-evasion-6d",
    "MultiVehicle9D-v0": "three-car-9d",
}


def _register() -> None:
    for env_id, scene in ENV_SCENES.items():
        if env_id in registry:
            continue
        register(
            id=env_id,
            entry_point="reach_envs.env:ReachEnv",
            vector_entry_point="reach_envs.vector:ReachVectorEnv",
            kwargs={"scene": scene},
        )


_register()

__all__ = ["ENV_SCENES"]
