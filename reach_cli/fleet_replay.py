"""``reach fleet-replay``: one collided episode of the fleet study (a file of ``OUT.collisions``),
replayed alone from the inputs it was given (:mod:`studies.fleet_collisions`): when and which cars
collided, and, with ``--gif``, the seconds before it."""

from __future__ import annotations

import argparse
from typing import Any

from reach.validation import check_output_path, positive_int_arg
from reach_cli.options import add_subparser

#: seconds before the first collision the GIF shows, by default
SECONDS = 6.0


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seconds: {text!r} is not a number") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"--seconds: must be positive and finite, got {text!r}")
    return value


def add_parser(sub: Any) -> None:
    p = add_subparser(sub, "fleet-replay", help="replay a collided episode of reach fleet-eval, with a GIF")
    p.add_argument("episode", help="an episode file from a study's OUT.collisions folder (.npz)")
    p.add_argument("--gif", default=None, help="draw the seconds before the first collision to this GIF")
    p.add_argument(
        "--seconds", type=_seconds, default=SECONDS, help=f"seconds before the collision drawn (default: {SECONDS:g})"
    )
    p.add_argument("--every", type=positive_int_arg, default=1, help="every k-th step a frame (default: 1)")
    p.add_argument(
        "--trace",
        type=positive_int_arg,
        default=None,
        metavar="K",
        help="also print the fleet filter's view of the colliding pair every K steps over those seconds: its "
        "distance, value and threshold, and the group of cars its active pairs join",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from reach_envs.fleet_render import render_fleet  # lazy: keeps `import reach_cli` light
    from reach_envs.recording import save_gif  # lazy: as above
    from studies import fleet_collisions as replays  # lazy: keeps `import reach_cli` light

    if args.gif is not None:
        check_output_path(args.gif, "--gif")
    episode = replays.load_episode(args.episode)
    hit = replays.first_collision(episode)
    meta, scene = episode.meta, episode.scene
    where = f"{scene.layout}, {scene.n_cars} cars, {meta.get('method')}: episode {meta.get('index')}"
    where += f" of the batch seeded {meta.get('seed')}"
    if hit["tick"] is None:
        print(f"{where}: no collision")
    else:
        pairs = ", ".join(f"car_{i + 1} and car_{j + 1}" for i, j in hit["pairs"])
        gap = f"closest {hit['distance']:.3f} apart, radius {hit['radius']:g}"
        print(f"{where}: {pairs} collided at t = {hit['time']:.2f} s (step {hit['tick']}; {gap})")
    if args.trace is not None and hit["tick"] is not None:
        i, j = hit["pairs"][0]
        pair = f"car_{i + 1}-car_{j + 1}"
        print(f"t s | {pair}: distance, value (threshold) | group: cars, active pairs, least value | inputs")
        for r in replays.conflict_trace(episode, args.seconds, args.trace):
            value = "n/a" if r["value"] is None else f"{r['value']:.3f} ({r['threshold']:.2f})"
            least = "n/a" if r["group_least"] is None else f"{r['group_least']:.3f}"
            ui, uj = r["inputs"]
            print(
                f"{r['time']:.2f} | {r['distance']:.3f}, {value} | {r['group_cars']}, {r['group_pairs']}, {least} "
                f"| {ui:+.2f}, {uj:+.2f}"
            )
    if args.gif is not None:
        frames = replays.window_frames(episode, args.seconds, args.every, render_fleet)
        save_gif(frames, args.gif, fps=1.0 / (scene.dt * args.every))
        print(f"{len(frames)} frames: {args.gif}")
    return 0
