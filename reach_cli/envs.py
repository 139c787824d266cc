"""``reach envs``: the registered environments and named scenes."""

from __future__ import annotations

import argparse
from typing import Any

from reach_cli.options import add_subparser


def add_parser(sub: Any) -> None:
    p = add_subparser(sub, "envs", help="list the registered environments and named scenes")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # lazy: gymnasium and the envs only when this command runs
    import reach_envs
    from reach_envs.scenes import SCENES

    print("Gymnasium environments:")
    for env_id, scene_name in reach_envs.ENV_SCENES.items():
        scene = SCENES[scene_name]()
        s = scene.system
        print(
            f"  {env_id:<20} scene={scene_name:<20} state={s.state_dim}D action={s.control_dim} "
            f"disturbance={scene.disturbance or 'none'} dt={scene.dt} horizon={scene.episode_horizon}"
        )
    print("Named scenes (gym.make(id, scene=NAME) or reach_envs.parallel.parallel_env(NAME)):")
    for name, factory in SCENES.items():
        scene = factory()
        print(f"  {name:<20} system={scene.system.name:<15} cars={len(scene.system.car_names)}")
    return 0
