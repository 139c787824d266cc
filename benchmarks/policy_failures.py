"""Where the gradient's policy fails although V is right: the 9D merge's switch, and the box's false-safe states.

Two measurements of a 9D value function (default: the shipped ``pretrained:multivehicle9d``):

``merge``: the switch filter in the three-car merge (500 starts outside the learned BRT, default
threshold, backup input ``u*``), traced step by step. For every episode the state where the switch
first hands over to ``u*`` is rolled out under the verification protocol (``u*`` from ``grad V``,
time-to-go counting down from the horizon, Euler at 0.0025 s), then held under each constant input
of the grid ``{-max, 0, +max}^3`` for the horizon, then rolled out under the greedy policy. It prints
how many episodes collide, how many hand-over states the gradient's policy loses, and how many of
those a constant input or the greedy policy saves.

``box``: the false-safe states among the first ``--samples`` uniform states of ``reach evaluate``
(seed 0: the model card's states): ``V > 0`` yet the ``u*`` rollout collides. Each is tried under
the 27 constant inputs, 500 random piecewise-constant bang-bang inputs (2, 4 or 8 pieces), and the
greedy policy. Those no input saves are a value error (``V`` should be <= 0 there); those some
input saves are a policy error (``V`` is right, ``u*`` is not).

``cost``: what the greedy policy costs, side by side in one process (run it on a quiet machine):
rollouts of 20,000 uniform 9D states under each policy (twice each, alternating, two threads), and
the switch filter in one Air3D-v0 and one MultiVehicle9D-v0 env under random nominal actions
(400 steps, one thread): mean time per step, and per step where the switch intervened.

    python benchmarks/policy_failures.py merge
    python benchmarks/policy_failures.py box --samples 100000
    python benchmarks/policy_failures.py cost
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
import torch

from reach.integrators import make_stepper
from reach.systems.arrays import TORCH
from reach.validation import positive_int_arg
from reach_envs.scenes import make_scene
from reach_envs.vector import ReachVectorEnv
from safety.filters.settings import FilterSettings
from safety.filters.wrappers import SafetyFilterVectorWrapper
from safety.value_loading import load_value_function
from safety.verification.rollout import rollout
from safety.verification.verify import sample_states, values_at
from studies.filter_episodes import outside_states
from studies.goal_tasks import make_task

DT = 0.0025  # the verification protocol's step


def held_safe(system, x0: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
    """Which states stay out of the failure set for the horizon under piecewise-constant inputs
    ``(pieces, N, m)`` (each held for an equal share of the horizon), Euler at ``DT``."""
    step = make_stepper(system, DT, "euler", TORCH)
    steps = round(system.horizon / DT)
    per_piece = -(-steps // inputs.shape[0])
    x = x0.double().clone()
    safe = system.failure_margin(x) > 0
    for k in range(steps):
        u = inputs[k // per_piece]
        x = TORCH.stack(step(TORCH.unbind(x), system.input_columns(u, system.control_bounds, "u"), []), like=x[:, 0])
        safe &= system.failure_margin(x) > 0
    return safe


def constant_inputs(system) -> torch.Tensor:
    """The ``3^m`` constant inputs ``{low, centre, high}^m``, shape ``(3^m, m)``."""
    box = system.control_bounds
    return torch.tensor(list(itertools.product(*zip(box.low, box.center, box.high))), dtype=torch.float64)


def saved_by_some_input(system, x: torch.Tensor, random_tries: int, seed: int = 0) -> torch.Tensor:
    """Which states some constant input, or one of ``random_tries`` random bang-bang inputs, keeps safe."""
    saved = torch.zeros(len(x), dtype=torch.bool)
    for u in constant_inputs(system):
        saved |= held_safe(system, x, u.expand(1, len(x), -1))
    box = system.control_bounds
    low, high = torch.tensor(box.low, dtype=torch.float64), torch.tensor(box.high, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    for i in range(random_tries):
        corners = torch.randint(0, 2, ((2, 4, 8)[i % 3], len(x), system.control_dim), generator=g).double()
        saved |= held_safe(system, x, low + (high - low) * corners)
    return saved


def merge(args: argparse.Namespace) -> None:
    vf = load_value_function(args.value_function).value_function
    system = vf.system
    scene = make_scene("three-car-merge")
    starts = outside_states(vf, args.episodes, 0.1, 0, scene)
    task = make_task(system)
    base = ReachVectorEnv(args.episodes, scene)
    env = SafetyFilterVectorWrapper(base, vf, settings=FilterSettings(policy="gradient"))
    env.reset(seed=0, options={"state": starts})
    task.reset(base.state, np.random.default_rng(0))
    active = np.ones(args.episodes, dtype=bool)
    collided = np.zeros(args.episodes, dtype=bool)
    handover = np.full((args.episodes, system.state_dim), np.nan)
    handover_value = np.full(args.episodes, np.nan)
    for k in range(scene.max_steps):
        before = base.state.copy()
        _, _, terminated, truncated, info = env.step(task.nominal_actions(base.state).astype(np.float32))
        first = active & info["filter_intervened"] & np.isnan(handover_value)
        handover[first], handover_value[first] = before[first], info["filter_value"][first]
        collided |= info["collision"] & active
        task.advance(base.state, info["control"], scene.dt, active & ~info["collision"], (k + 1) * scene.dt)
        active &= ~(terminated | truncated)
        if not active.any():
            break
    took = ~np.isnan(handover_value)
    x = torch.tensor(handover[took], dtype=torch.float32)
    lost = rollout(vf, x, progress=False).collided.numpy()
    greedy = rollout(vf, x, policy="greedy", progress=False).collided.numpy()
    saved = saved_by_some_input(system, x[lost], 0).numpy()
    print(f"{args.value_function}, three-car merge, {args.episodes} starts outside the learned BRT, switch with u*:")
    print(f"  collided: {collided.sum()} episodes; the switch handed over in {took.sum()}")
    print(
        f"  V at the first hand-over of the collided episodes: {np.nanmin(handover_value[collided]):.4f} "
        f"to {np.nanmax(handover_value[collided]):.4f}"
    )
    print(
        f"  rolled out from the hand-over state under u* (verification protocol): {lost.sum()} collide, "
        f"{(lost & collided[took]).sum()} of them in episodes the switch lost"
    )
    print(f"  of those {lost.sum()}, a constant input keeps {saved.sum()} safe for the horizon")
    print(f"  under the greedy policy from the same hand-over states: {greedy.sum()} collide")


def box(args: argparse.Namespace) -> None:
    vf = load_value_function(args.value_function).value_function
    system = vf.system
    x = sample_states(system, args.samples, 0)
    v = values_at(vf, x, system.horizon)
    positive = v > 0
    start = time.perf_counter()
    result = rollout(vf, x[positive], chunk_size=262144, progress=False)
    false_safe = x[positive][result.collided]
    fv = v[positive][result.collided]
    saved = saved_by_some_input(system, false_safe, args.random_tries)
    greedy = rollout(vf, false_safe, policy="greedy", progress=False).collided
    print(
        f"{args.value_function}: {len(false_safe)} false-safe states among {args.samples} "
        f"({time.perf_counter() - start:.0f} s)"
    )
    print(
        f"  no input tried saves {(~saved).sum()} (value errors): "
        f"V from {fv[~saved].min():.4f} to {fv[~saved].max():.4f}"
    )
    if saved.any():
        print(
            f"  some input saves {saved.sum()} (policy errors): V from {fv[saved].min():.4f} to {fv[saved].max():.4f}"
        )
    print(f"  the greedy policy saves {(~greedy).sum()} of them ({(~greedy & saved).sum()} of the policy errors)")


def cost(args: argparse.Namespace) -> None:
    import gymnasium as gym

    import reach_envs  # noqa: F401  (registers the envs)
    from safety.filters.wrappers import SafetyFilterWrapper

    vf = load_value_function(args.value_function).value_function
    x = sample_states(vf.system, args.samples, 0)
    torch.set_num_threads(2)
    for policy in ("gradient", "greedy", "gradient", "greedy"):
        start = time.perf_counter()
        r = rollout(vf, x, policy=policy, chunk_size=262144, progress=False)
        print(
            f"rollouts of {args.samples} states, {policy}: {time.perf_counter() - start:.1f} s "
            f"({r.state_steps} state-steps)"
        )
    torch.set_num_threads(1)
    for env_id in ("Air3D-v0", "MultiVehicle9D-v0"):
        for policy in ("gradient", "greedy"):
            env = SafetyFilterWrapper(gym.make(env_id), settings=FilterSettings(policy=policy))
            env.reset(seed=0)
            env.action_space.seed(0)
            steps = interventions = 0
            acting = 0.0
            start = time.perf_counter()
            for _ in range(400):
                t0 = time.perf_counter()
                _, _, terminated, truncated, info = env.step(env.action_space.sample())
                steps += 1
                if info["filter_intervened"]:
                    interventions += 1
                    acting += time.perf_counter() - t0
                if terminated or truncated:
                    env.reset()
            mean = 1e3 * (time.perf_counter() - start) / steps
            print(
                f"{env_id}, switch with the {policy} input: {mean:.2f} ms a step, "
                f"{1e3 * acting / max(interventions, 1):.2f} ms a step where it intervened "
                f"({interventions} of {steps}), one thread"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    m = sub.add_parser("merge", help="the switch in the three-car merge, traced")
    m.add_argument("--episodes", type=positive_int_arg, default=500)
    b = sub.add_parser("box", help="the false-safe states among the card's uniform states")
    b.add_argument("--samples", type=positive_int_arg, default=100_000)
    b.add_argument("--random-tries", type=int, default=500)
    c = sub.add_parser("cost", help="rollout and filter time of the two policies, side by side")
    c.add_argument("--samples", type=positive_int_arg, default=20_000)
    for p in (m, b, c):
        p.add_argument("--value-function", default="pretrained:multivehicle9d")
    args = parser.parse_args()
    torch.set_num_threads(1)
    {"merge": merge, "box": box, "cost": cost}[args.what](args)


if __name__ == "__main__":
    main()
