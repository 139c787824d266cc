"""The fleet filter's decision time now against an earlier commit's, alternating on the same states.

Run: ``python benchmarks/fleet_decision_ab.py --rev 0a10a13~1 [--layout circle-swap --cars 64 --ticks 900 --every 3]``

Why: decision time on a shared 2-core machine moves with everything else running on it, so two
tables measured at different times do not compare. Here both versions decide the same states in
one process, alternating which goes first, so the load falls on both alike.

What it does:

1. Drives one episode of the scene (seed ``--seed``) with the current fleet filter for ``--ticks``
   steps and keeps every ``--every``-th state (batch 1).
2. Loads the modules ``--modules`` (default: the fleet's greedy policy, ``safety/fleet/greedy.py``)
   as they were at ``--rev`` (``git show REV:PATH``, into a temporary folder; nothing is written
   to the repository) and swaps each in for the current one in turn.
3. Times each decision (``time.perf_counter``, one torch thread) under both versions, and checks that
   both return the same inputs to the bit (a speed change must not change a decision; it says so
   where they differ).

It prints the median, mean and 99th percentile per version and their ratio.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from reach_envs.fleet import FleetSimulator, goal_seeking
from reach_envs.fleet_scenes import LAYOUTS, FleetScene
from studies.fleet_methods import make_method

ROOT = Path(__file__).resolve().parents[1]

#: where a swapped module's functions are looked up by the filter, per module path
USERS = {"safety/fleet/greedy.py": ("safety.fleet.filter", ("joint_greedy",))}


def _module_at(rev: str, path: str, folder: Path) -> object:
    source = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True, capture_output=True, text=True)
    file = folder / Path(path).name
    file.write_text(source.stdout)
    spec = importlib.util.spec_from_file_location(f"_ab_{Path(path).stem}", file)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _accepting(function: Callable[..., Any]) -> Callable[..., Any]:
    """``function`` called with only as many positional arguments as it takes: an earlier version may
    lack a trailing option the caller now passes (its default, as this comparison runs the
    current defaults)."""
    count = len(inspect.signature(function).parameters)

    def call(*args: Any) -> Any:
        return function(*args[:count])

    return call


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", required=True, help="the earlier commit")
    parser.add_argument("--modules", default="safety/fleet/greedy.py", help=f"comma-separated, among {list(USERS)}")
    parser.add_argument("--layout", choices=LAYOUTS, default="circle-swap")
    parser.add_argument("--cars", type=int, default=64)
    parser.add_argument("--ticks", type=int, default=900)
    parser.add_argument("--every", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    scene = FleetScene(layout=args.layout, n_cars=args.cars)
    decide = make_method("fleet", scene)
    sim = FleetSimulator(scene)
    x, goals = scene.sample(1, np.random.default_rng(args.seed))
    present = torch.ones(1, scene.n_cars, dtype=torch.bool)
    states = []
    for k in range(min(args.ticks, scene.max_steps)):
        if not bool(present.any()):
            break
        u, _ = decide(x, goal_seeking(x, goals, scene), present)
        if k % args.every == 0:
            states.append((x, present))
        x, _, _, present = sim.step(x, u, present, goals)
    swaps = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.modules.split(","):
            user, names = USERS[path]
            old = _module_at(args.rev, path, Path(tmp))
            owner = sys.modules[user]
            swaps += [(owner, name, _accepting(getattr(old, name)), getattr(owner, name)) for name in names]

        def use(version: int) -> None:
            for owner, name, *impl in swaps:
                setattr(owner, name, impl[version])

        times: dict[str, list[float]] = {args.rev: [], "now": []}
        differ = 0
        for k, (x, present) in enumerate(states):
            nominal = goal_seeking(x, goals, scene)
            out = {}
            for version in (0, 1) if k % 2 else (1, 0):
                use(version)
                start = time.perf_counter()
                out[version], _ = decide(x, nominal, present)
                times[(args.rev, "now")[version]].append(time.perf_counter() - start)
            differ += int(not torch.equal(out[0], out[1]))
        use(1)
    print(
        f"{args.layout}, {args.cars} cars: {len(states)} decisions (one every {args.every} of {args.ticks} steps, seed "
        f"{args.seed}), batch 1, one torch thread, alternating; modules at {args.rev}: {args.modules}"
    )
    stats = {}
    for name, values in times.items():
        ms = np.asarray(values) * 1e3
        stats[name] = float(np.median(ms))
        p99 = np.percentile(ms, 99)
        print(f"  {name:>12}: median {stats[name]:.2f} ms, mean {ms.mean():.2f} ms, p99 {p99:.1f} ms")
    print(f"  median ratio now / {args.rev}: {stats['now'] / stats[args.rev]:.2f}; decisions that differ: {differ}")


if __name__ == "__main__":
    main()
