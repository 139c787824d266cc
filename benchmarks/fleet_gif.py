"""One fleet episode as a GIF (docs/fleet_32.gif): ``studies.fleet_plots.record_fleet_gif``.

Run (the docs' GIF)::

    python benchmarks/fleet_gif.py --layout random-goals --cars 32 --method fleet --seed 0 --every 4 \
        --out docs/fleet_32.gif

Prints what happened in the episode: cars that collided, cars at their goal, steps, frames.
"""

from __future__ import annotations

import argparse

from reach_envs.fleet_scenes import LAYOUTS, FleetScene
from studies.fleet_plots import record_fleet_gif
from studies.fleet_settings import METHODS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--layout", choices=LAYOUTS, default="random-goals")
    parser.add_argument("--cars", type=int, default=32)
    parser.add_argument("--method", choices=METHODS, default="fleet")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--every", type=int, default=4, help="every k-th step a frame")
    parser.add_argument("--out", default="fleet.gif")
    args = parser.parse_args()
    scene = FleetScene(layout=args.layout, n_cars=args.cars)
    print(record_fleet_gif(scene, args.method, args.out, seed=args.seed, every=args.every))


if __name__ == "__main__":
    main()
