"""The price of composition: the fleet filter (pairs) against the learned N-car filters on N-car merges.

Run: ``python benchmarks/fleet_composition.py [--cars 3,4,5] [--episodes 1000] [--seed 0]``

The union of pairwise values is an inner bound of the N-car BRT: where the learned N-car value is
trusted (``reach pretrained`` shows its verdict: the capped 9D network under the greedy policy
passes), the two filters can disagree, and this counts how often and what each lets through. The
shipped 12D and 15D models fail the trust bar; this benchmark opts in to them by name
(``allow_untrusted=True``), prints their verdicts, and measures them beside the fleet filter. What
it does, for each N in ``--cars``:

1. Draws ``--episodes`` starts of the N-car merge: N cars evenly spaced 0.8 from the centre and
   heading in (at N = 3 the ``three-car-merge`` scene's poses), with that scene's uniform jitter
   (0.05 in position, 0.1 rad in heading); each car's goal the antipode of its start; the scene's
   2-second horizon and its step (0.02 s): no car reaches its goal, all N stay present.
2. Rolls every start out (``reach_envs.fleet.rollout``, the cars' own stepper) unfiltered, under the
   fleet filter (``safety.fleet.FleetFilter`` over ``pretrained:relativepair``, its defaults at that
   step), and under the switch filter the ``MultiVehicle{3N}D-v0`` wrapper builds (the card's
   ``filter_source``, its default policy and threshold at that step).
3. On every state either filtered rollout visits, asks both filters whether they intervene (any car)
   and counts the states where they disagree, each way.
Prints the collision count of each method with its 95 % Wilson interval, the disagreement counts
and the wall time. Torch threads: 1.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from reach.systems import MultiVehicle9D, MultiVehicle12D, MultiVehicle15D
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

#: the learned N-car systems, by N
LEARNED = {3: MultiVehicle9D, 4: MultiVehicle12D, 5: MultiVehicle15D}


def merge_starts(n: int, episodes: int, seed: int) -> torch.Tensor:
    """``(episodes, 3n)`` starts of the n-car merge: n poses 0.8 from the centre heading in (at n = 3
    the ``three-car-merge`` scene's own), plus that scene's uniform jitter (positions, then headings)."""
    merge = SCENES["three-car-merge"]().initial_state
    angles = [math.pi / 2 + 2 * math.pi * k / n for k in range(n)]
    xy = [v for a in angles for v in (0.8 * math.cos(a), 0.8 * math.sin(a))]
    base = np.asarray(xy + [math.remainder(a + math.pi, 2 * math.pi) for a in angles])
    if n == 3:
        assert np.allclose(base, merge.state)  # the registered scene's poses
    jitter = np.asarray([merge.jitter[0]] * (2 * n) + [merge.jitter[-1]] * n, dtype=np.float64)
    rng = np.random.default_rng(seed)
    return torch.from_numpy(base + rng.uniform(-jitter, jitter, size=(episodes, base.size)))


def compare(n: int, episodes: int, seed: int) -> None:
    """Step 1 to 3 of the module docstring for ``n`` cars, printed."""
    merge = SCENES["three-car-merge"]()
    scene = FleetScene(layout="circle-swap", n_cars=n, dt=merge.dt, horizon=merge.episode_horizon)
    x0 = merge_starts(n, episodes, seed)
    goals = -x0[:, : 2 * n].reshape(-1, n, 2)
    fleet = FleetFilter(fleet_value(scene), FleetFilterSettings(dt=scene.dt))
    system = LEARNED[n]()
    name = f"multivehicle{3 * n}d"
    source = pretrained.for_env(f"MultiVehicle{3 * n}D-v0", system, allow_untrusted=True)  # opted in by name
    learned = load_value_function(source, system=system).value_function
    nd = SafetyFilter(learned, threshold=default_threshold(learned.system, scene.dt))
    horizon = learned.system.horizon

    def with_fleet(x: torch.Tensor, g: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        return fleet(x, 1.0, goal_seeking(x, g, scene), present)[0]

    def with_learned(x: torch.Tensor, g: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        return nd(x, horizon, goal_seeking(x, g, scene))[0].to(x.dtype)

    label = f"{3 * n}d"
    print(f"{n}-car merge, {episodes} episodes, seed {seed}, dt {scene.dt}, horizon {scene.horizon} s")
    print(f"{label} filter source: {source} (its card's verdict: {pretrained.card(name).verdict.line()})")
    visited = []
    for method, controller in (("none", None), ("fleet", with_fleet), (label, with_learned)):
        start = time.perf_counter()
        out = rollout(scene, x0, goals, controller, record=method != "none")
        wall = time.perf_counter() - start
        k = int(out.any_collision.sum())
        lo, hi = wilson_interval(k, episodes)
        print(f"{method:>6}: {k} of {episodes} episodes collide [{lo:.4f}, {hi:.4f}], {wall:.1f} s")
        if out.states is not None:
            visited.append(out.states[:, ~out.any_collision].reshape(-1, 3 * n))
    states = torch.cat(visited)
    u0 = goal_seeking(states, -states[:, : 2 * n].reshape(-1, n, 2), scene)
    fleet_acts = fleet(states, 1.0, u0)[1].intervened.any(1)
    learned_acts = nd(states, horizon, u0)[1].intervened
    print(
        f"states visited by the collision-free filtered episodes: {states.shape[0]}; the fleet filter "
        f"intervenes on {int(fleet_acts.sum())}, the {label} filter on {int(learned_acts.sum())}; only the "
        f"fleet filter: {int((fleet_acts & ~learned_acts).sum())}, only the {label} filter: "
        f"{int((learned_acts & ~fleet_acts).sum())}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cars", default="3", help="comma-separated fleet sizes among 3, 4, 5 (default: 3)")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    sizes = [int(v) for v in args.cars.split(",")]
    if any(n not in LEARNED for n in sizes):
        parser.error(f"--cars must be among {sorted(LEARNED)}, got {args.cars!r}")
    torch.set_num_threads(1)
    for n in sizes:
        compare(n, args.episodes, args.seed)


if __name__ == "__main__":
    main()
