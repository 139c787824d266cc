"""``reach record``: run one episode of an environment and save it as a GIF."""

from __future__ import annotations

import argparse
from typing import Any

from reach.validation import check_output_path, positive_int_arg, seed_arg
from reach_cli.options import add_subparser


def add_parser(sub: Any) -> None:
    p = add_subparser(sub, "record", help="run one episode and save it as a GIF")
    p.add_argument("env", nargs="?", default="Air3D-v0", help="Gymnasium id (default: Air3D-v0)")
    p.add_argument("--scene", default=None, help="named scene to run instead of the id's default")
    p.add_argument("--policy", choices=["straight", "random"], default="straight", help="agent policy")
    p.add_argument("--seed", type=seed_arg, default=0)
    p.add_argument("--every", type=positive_int_arg, default=1, help="keep every N-th frame")
    p.add_argument("--out", default="episode.gif", help="GIF path")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import gymnasium as gym  # lazy: gymnasium only when this command runs

    # lazy: the envs only when this command runs
    import reach_envs
    from reach_envs.recording import record_episode

    check_output_path(args.out, "GIF")
    if args.env not in gym.registry:
        known = ", ".join(reach_envs.ENV_SCENES)
        raise ValueError(f"unknown environment {args.env!r}; registered: {known}")
    kwargs = {"scene": args.scene} if args.scene else {}
    try:
        env = gym.make(args.env, render_mode="rgb_array", **kwargs)
    except gym.error.Error as err:  # Gymnasium's own errors are not ValueErrors
        raise ValueError(f"{args.env}: {err}") from err
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
