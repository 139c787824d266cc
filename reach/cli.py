"""``reach``: the command line of the reach toolkit.

Subcommands only parse arguments and call library functions. Present: ``envs`` (list environments
and scenes) and ``record`` (run an episode and save a GIF). Later subcommands (groundtruth, train,
evaluate, ...) arrive with their issues.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence


def _cmd_envs(args: argparse.Namespace) -> int:
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


def _cmd_record(args: argparse.Namespace) -> int:
    import gymnasium as gym

    import reach_envs  # noqa: F401  (registers the environments)
    from reach_envs.recording import record_episode

    kwargs = {"scene": args.scene} if args.scene else {}
    env = gym.make(args.env, render_mode="rgb_array", **kwargs)
    if args.policy == "random":
        env.action_space.seed(args.seed)

        def policy(obs):
            return env.action_space.sample()
    else:
        policy = None
    summary = record_episode(env, args.out, policy=policy, seed=args.seed, every=args.every)
    env.close()
    print(
        f"wrote {summary['path']}: {summary['steps']} steps, {summary['frames']} frames, "
        f"collision={summary['collision']}"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="reach", description="Neural Hamilton-Jacobi reachability toolkit.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser("envs", help="list the registered environments and named scenes")
    p.set_defaults(func=_cmd_envs)

    p = sub.add_parser("record", help="run one episode and save it as a GIF")
    p.add_argument("env", nargs="?", default="Air3D-v0", help="Gymnasium id (default: Air3D-v0)")
    p.add_argument("--scene", default=None, help="named scene to run instead of the id's default")
    p.add_argument("--policy", choices=["straight", "random"], default="straight", help="agent policy")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--every", type=int, default=1, help="keep every N-th frame")
    p.add_argument("--out", default="episode.gif", help="GIF path")
    p.set_defaults(func=_cmd_record)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except ValueError as err:
        print(f"reach {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
