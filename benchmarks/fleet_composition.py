"""The price of composition: the fleet filter (pairs) against the learned 9D filter on the 3-car merge.

Run: ``python benchmarks/fleet_composition.py [--episodes 1000] [--seed 0]``

The union of pairwise values is an inner bound of the 3-car BRT: where the 9D value is trusted
(``reach pretrained`` shows its verdict: the capped 9D network under the greedy policy passes), the
two filters can disagree, and this counts how often and what each lets through. What it does:

1. Draws ``--episodes`` starts of the ``three-car-merge`` scene (its fixed poses, 0.8 from the centre
   and heading in, with the scene's uniform jitter), each car's goal the antipode of its start; the
   scene's 2-second horizon and its step (0.02 s): no car reaches its goal, all three stay present.
2. Rolls every start out (``reach_envs.fleet.rollout``, the cars' own stepper) unfiltered, under the
   fleet filter (``safety.fleet.FleetFilter`` over ``pretrained:relativepair``, its defaults at that
   step), and under the 9D switch filter the ``MultiVehicle9D-v0`` wrapper builds by default (the
   card's ``filter_source``, its default policy and threshold at that step).
3. On every state either filtered rollout visits, asks both filters whether they intervene (any car)
   and counts the states where they disagree, each way.
Prints the collision count of each method with its 95 % Wilson interval, the disagreement counts
and the wall time. Torch threads: 1.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from reach.systems import MultiVehicle9D
from reach_envs.fleet import goal_seeking, rollout
from reach_envs.fleet_scenes import FleetScene
from reach_envs.scenes import SCENES
from safety.filters.base import SafetyFilter
from safety.filters.settings import default_threshold
from safety.fleet import FleetFilter, FleetFilterSettings
from safety.value_loading import load_value_function
from safety.verification.metrics import wilson_interval
from studies.fleet_methods import fleet_value
from training import pretrained


def merge_starts(episodes: int, seed: int) -> torch.Tensor:
    """``(episodes, 9)`` starts of the three-car merge: its poses plus its uniform jitter."""
    start = SCENES["three-car-merge"]().initial_state
    rng = np.random.default_rng(seed)
    base = np.asarray(start.state)
    jitter = np.broadcast_to(np.asarray(start.jitter, dtype=np.float64), base.shape)
    return torch.from_numpy(base + rng.uniform(-jitter, jitter, size=(episodes, base.size)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    merge = SCENES["three-car-merge"]()
    scene = FleetScene(layout="circle-swap", n_cars=3, dt=merge.dt, horizon=merge.episode_horizon)
    x0 = merge_starts(args.episodes, args.seed)
    goals = -x0[:, :6].reshape(-1, 3, 2)
    fleet = FleetFilter(fleet_value(scene), FleetFilterSettings(dt=scene.dt))
    source = pretrained.for_env("MultiVehicle9D-v0", MultiVehicle9D())
    learned = load_value_function(source, system=MultiVehicle9D()).value_function
    nine = SafetyFilter(learned, threshold=default_threshold(learned.system, scene.dt))
    horizon = learned.system.horizon

    def with_fleet(x: torch.Tensor, g: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        return fleet(x, 1.0, goal_seeking(x, g, scene), present)[0]

    def with_nine(x: torch.Tensor, g: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        return nine(x, horizon, goal_seeking(x, g, scene))[0].to(x.dtype)

    print(f"3-car merge, {args.episodes} episodes, seed {args.seed}, dt {scene.dt}, horizon {scene.horizon} s")
    print(f"9D filter source: {source} (its card's verdict: {pretrained.card('multivehicle9d').verdict})")
    visited = []
    for name, controller in (("none", None), ("fleet", with_fleet), ("9d", with_nine)):
        start = time.perf_counter()
        out = rollout(scene, x0, goals, controller, record=name != "none")
        wall = time.perf_counter() - start
        k = int(out.any_collision.sum())
        lo, hi = wilson_interval(k, args.episodes)
        print(f"{name:>6}: {k} of {args.episodes} episodes collide [{lo:.4f}, {hi:.4f}], {wall:.1f} s")
        if out.states is not None:
            visited.append(out.states[:, ~out.any_collision].reshape(-1, 9))
    states = torch.cat(visited)
    u0 = goal_seeking(states, -states[:, :6].reshape(-1, 3, 2), scene)
    fleet_acts = fleet(states, 1.0, u0)[1].intervened.any(1)
    nine_acts = nine(states, horizon, u0)[1].intervened
    print(
        f"states visited by the collision-free filtered episodes: {states.shape[0]}; the fleet filter "
        f"intervenes on {int(fleet_acts.sum())}, the 9D filter on {int(nine_acts.sum())}; only the fleet "
        f"filter: {int((fleet_acts & ~nine_acts).sum())}, only the 9D filter: {int((nine_acts & ~fleet_acts).sum())}"
    )


if __name__ == "__main__":
    main()
