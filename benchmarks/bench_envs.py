"""Environment throughput: single-env steps/s against Pendulum-v1, vector-env car-steps/s, effect costs.

Run: ``python benchmarks/bench_envs.py`` (add ``--quick`` for a fast smoke run).

Every figure is measured in this run: the median of ``--repeats`` timed blocks, each ``--steps``
steps with pre-sampled random actions, resetting whenever an episode ends (reset time included).
Environments are built with ``gym.make`` (default wrappers: order enforcing, passive env checker),
the same way for Pendulum-v1, so wrapper overhead is on both sides of the ratio.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import gymnasium as gym
import numpy as np
import torch

import reach

CARS = {"Air3D-v0": 2, "MultiVehicle6D-v0": 2, "MultiVehicle9D-v0": 3}


def _block(env: gym.Env, actions: list) -> float:
    """Seconds per step over one block of pre-sampled actions, resetting when an episode ends."""
    t0 = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    return (time.perf_counter() - t0) / len(actions)


def time_single(env: gym.Env, steps: int, repeats: int, baseline: gym.Env | None = None) -> tuple[float, float]:
    """Median seconds per step, and the median ratio to ``baseline`` timed in alternating blocks.

    Alternating blocks of the env and the baseline makes the ratio robust to the load drifting
    on a shared machine.
    """
    prepared = []
    for e in (env, baseline) if baseline is not None else (env,):
        e.reset(seed=0)
        e.action_space.seed(0)
        acts = [e.action_space.sample() for _ in range(steps)]
        _block(e, acts[:500])  # warm-up
        prepared.append((e, acts))
    times, ratios = [], []
    for _ in range(repeats):
        t = _block(*prepared[0])
        times.append(t)
        if baseline is not None:
            ratios.append(t / _block(*prepared[1]))
    return statistics.median(times), (statistics.median(ratios) if ratios else float("nan"))


def time_vector(env_id: str, num_envs: int, steps: int, repeats: int) -> float:
    venv = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    venv.action_space.seed(0)
    actions = [venv.action_space.sample() for _ in range(8)]
    for k in range(10):
        venv.step(actions[k % 8])
    blocks = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for k in range(steps):
            venv.step(actions[k % 8])
        blocks.append((time.perf_counter() - t0) / steps)
    return statistics.median(blocks)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20_000, help="steps per timed block (single envs)")
    parser.add_argument("--vector-steps", type=int, default=200, help="steps per timed block (vector envs)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 256, 4096])
    parser.add_argument("--quick", action="store_true", help="tiny run to check the script works")
    args = parser.parse_args()
    if args.quick:
        args.steps, args.vector_steps, args.repeats, args.num_envs = 500, 5, 1, [16]

    print(f"# reach {reach.__version__} environment benchmark")
    print(
        f"python {platform.python_version()}, numpy {np.__version__}, gymnasium {gym.__version__}, "
        f"torch {torch.__version__}, {os.cpu_count()} CPUs ({platform.processor() or platform.machine()}); "
        f"median of {args.repeats} blocks\n"
    )

    print("## Single environment (gym.make, random actions, resets included)\n")
    print("| env | us/step | steps/s | x Pendulum-v1 (median of paired blocks) |")
    print("|---|---:|---:|---:|")
    pendulum = gym.make("Pendulum-v1")
    base, _ = time_single(pendulum, args.steps, args.repeats)
    print(f"| Pendulum-v1 | {base * 1e6:.1f} | {1 / base:,.0f} | 1.00 |")
    for env_id in CARS:
        t, ratio = time_single(gym.make(env_id), args.steps, args.repeats, baseline=pendulum)
        print(f"| {env_id} | {t * 1e6:.1f} | {1 / t:,.0f} | {ratio:.2f} |")
    print("\n## Cost of each effect (Air3D-v0 single env)\n")
    print("| scene | us/step |")
    print("|---|---:|")
    variants = [
        ("no disturbance, no collision termination", {"disturbance": None, "terminate_on_collision": False}),
        ("+ collision termination", {"disturbance": None}),
        ("+ pursuit disturbance (default scene)", {}),
        ("+ random disturbance instead", {"disturbance": "random"}),
        ("+ process noise", {"process_noise": 0.05}),
        ("+ arena bounds", {"process_noise": 0.05, "arena": 2.0}),
        ("default scene, Euler instead of RK4", {"integrator": "euler"}),
    ]
    for label, overrides in variants:
        t, _ = time_single(gym.make("Air3D-v0", **overrides), args.steps, args.repeats)
        print(f"| {label} | {t * 1e6:.1f} |")
    env = gym.make("Air3D-v0", scene="head-on", render_mode="rgb_array")
    env.reset(seed=0)
    env.render()
    n = 20 if not args.quick else 3
    t0 = time.perf_counter()
    for _ in range(n):
        if any(env.step(np.zeros(2, dtype=np.float32))[2:4]):
            env.reset()
        env.render()
    print(f"| head-on with trails, step + rgb_array render | {(time.perf_counter() - t0) / n * 1e6:.0f} |")

    print("\n## Vector environments (one NumPy batch; car-steps = envs x cars x steps)\n")
    print("| env | num_envs | vector steps/s | env-steps/s | car-steps/s |")
    print("|---|---:|---:|---:|---:|")
    for env_id, cars in CARS.items():
        for num_envs in args.num_envs:
            t = time_vector(env_id, num_envs, args.vector_steps, args.repeats)
            print(f"| {env_id} | {num_envs} | {1 / t:,.0f} | {num_envs / t:,.0f} | {num_envs * cars / t:,.0f} |")


if __name__ == "__main__":
    main()
