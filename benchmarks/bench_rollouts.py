"""Rollout throughput: our engine against a DeepReach-style loop, same network, same states.

Run: ``python benchmarks/bench_rollouts.py`` (9D, 4x512 sine network, 400 Euler steps of 0.0025 s;
``--states 100000`` for the full figure, ``--quick`` for a smoke run).

Three ways to roll out the same states under the optimal policy of the same network:

* ``deepreach-style``: what DeepReach's verification loop does - every state for every step, the
  network's parameters requiring grad, ``(t, x)`` inputs requiring grad and the input gradient by
  ``torch.autograd.grad(..., create_graph=True)`` (its ``diff_operators.jacobian``), in chunks of
  the same size as ours;
* ``reach, no early exit``: our fused value-and-gradient pass (no autograd graph of the network),
  still every state for every step;
* ``reach``: the default engine, which also stops trajectories whose outcome is decided (collided,
  or unable to reach a collision in the time left whatever the inputs: the system's margin floor,
  which for cars accounts for their headings and turn rates);
* ``reach, bfloat16 matmuls`` (opt-in ``matmul_precision="bfloat16"``): the default engine with the
  network's hidden products in bfloat16; not exact, so the script counts the states whose outcome
  differs from float32.

It prints wall time, state-steps evaluated, rollouts x steps per second (N x 400 / wall) and the
speed-up over the DeepReach-style loop, and checks the three agree on which states collide. The
network is freshly initialised (no trained 9D network ships with the repo), which matters for the
early-exit share: a trained policy avoids more collisions, so more trajectories run their full length.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import torch

from reach.systems import make_system
from safety.verification.rollout import num_steps, rollout
from training import NeuralValueFunction, ValueNetwork


def deepreach_style(net: ValueNetwork, states: torch.Tensor, dt: float, chunk: int) -> torch.Tensor:
    """Every state, every step, autograd with ``create_graph=True``; returns who collided."""
    system = net.system
    horizon = system.horizon
    steps = num_steps(horizon, dt)
    collided = []
    for x in states.split(chunk):
        hit = system.failure_margin(x) <= 0
        for k in range(steps):
            t = torch.full((x.shape[0], 1), horizon - k * dt)
            coords = torch.cat([t, x], dim=-1).detach().requires_grad_(True)
            v = net(coords[:, 1:], coords[:, 0])
            (grad,) = torch.autograd.grad(v, coords, torch.ones_like(v), create_graph=True)
            p = grad[:, 1:].detach()
            u = system.optimal_control(x, p)
            x = system.wrap(x + dt * system.dynamics(x, u, None))
            hit |= system.failure_margin(x) <= 0
        collided.append(hit)
    return torch.cat(collided)


def cpu_description() -> str:
    """The CPU's model name and its widest vector / bfloat16 instruction sets (Linux), for the header."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    model = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")), "")
    flags = set(next((line.split(":", 1)[1].split() for line in info.splitlines() if line.startswith("flags")), []))
    wanted = ("avx2", "avx512f", "avx512_bf16", "amx_bf16")
    return f"{model or platform.machine()} ({', '.join(f for f in wanted if f in flags) or 'no AVX2'})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--system", default="multivehicle9d")
    parser.add_argument("--states", type=int, default=10_000)
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--layout", default="ssssl")
    parser.add_argument("--dt", type=float, default=0.0025)
    parser.add_argument("--chunk-size", type=int, default=16384)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-baseline", action="store_true", help="time only our engine")
    parser.add_argument(
        "--skip-bfloat16",
        action="store_true",
        help="leave out the bfloat16 row (CPUs without bf16 dot products emulate it, many times slower)",
    )
    parser.add_argument("--quick", action="store_true", help="smoke run: 500 states, width 64")
    args = parser.parse_args()
    if args.quick:
        args.states, args.width = 500, 64
    system = make_system(args.system)
    torch.manual_seed(args.seed)
    net = ValueNetwork(system, args.layout, width=args.width)
    vf = NeuralValueFunction(net)
    states = system.sample_states(args.states, generator=torch.Generator().manual_seed(args.seed))
    steps = num_steps(system.horizon, args.dt)
    print(
        f"# {args.system}, {args.layout} width {args.width}, {args.states} states x {steps} Euler steps "
        f"(dt {args.dt}), chunk {args.chunk_size}; torch {torch.__version__}, {os.cpu_count()} CPUs, "
        f"{cpu_description()}, threads {torch.get_num_threads()}"
    )
    rows = []
    results = {}
    engines = [("reach", True, "float32"), ("reach, no early exit", False, "float32")]
    if not args.skip_bfloat16:
        engines.append(("reach, bfloat16 matmuls", True, "bfloat16"))
    for label, early, precision in engines:
        r = rollout(
            vf,
            states,
            dt=args.dt,
            chunk_size=args.chunk_size,
            early_exit=early,
            progress=False,
            matmul_precision=precision,
        )
        results[label] = r.collided
        rows.append((label, r.wall_time, r.state_steps))
    if not args.skip_baseline:
        start = time.perf_counter()
        results["deepreach-style"] = deepreach_style(net, states, args.dt, args.chunk_size)
        rows.append(("deepreach-style", time.perf_counter() - start, args.states * steps))
    base = dict((label, wall) for label, wall, _ in rows).get("deepreach-style")
    print("| method | wall (s) | state-steps evaluated | rollouts x steps / s | speed-up |")
    print("|---|---|---|---|---|")
    for label, wall, work in rows:
        speedup = f"{base / wall:.2f}x" if base else "-"
        print(
            f"| {label} | {wall:.1f} | {work:,} ({work / (args.states * steps):.0%}) | "
            f"{args.states * steps / wall:,.0f} | {speedup} |"
        )
    ref = results["reach"]
    for label, collided in results.items():
        agree = (collided == ref).float().mean().item()
        differ = int((collided != ref).sum())
        print(
            f"# {label}: collision rate {collided.float().mean().item():.4f}, agrees with reach on {agree:.4%} "
            f"({differ} outcomes differ)"
        )


if __name__ == "__main__":
    main()
