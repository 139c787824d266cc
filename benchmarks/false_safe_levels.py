"""How close to zero a value function's false-safe states sit: false safe and safe volume by level.

Run: ``python benchmarks/false_safe_levels.py pretrained:multivehicle9d [--samples 100000]
[--levels 0,0.005,0.01,0.02,0.05] [--pairwise runs/pair_gt.npz]``

``reach evaluate`` reports the false-safe share at level 0: states with ``V > 0`` whose rollout
under the value function's own policy collides. This script rolls out the same uniform states
(``--seed``, the same as ``reach evaluate``'s) once and prints, for each level, the share of states
with ``V > level`` that collide and the share of the box above the level: what a filter threshold
or a certified level buys. It also prints quantiles of ``V`` over the false-safe states, and with
``--pairwise`` the false-safe share of ``min(V, V_union)`` (same rollouts: the network's policy).
"""

from __future__ import annotations

import argparse
import time

import torch

from safety.value_loading import load_value_function
from safety.verification.rollout import rollout
from safety.verification.verify import sample_states
from studies.batch_verification import pairwise_union_values


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", help="a value function: run directory, checkpoint, pretrained:NAME, .npz")
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--levels", default="0,0.005,0.01,0.02,0.05")
    parser.add_argument("--pairwise", default=None, help="two-car grid .npz: also the union-capped value")
    args = parser.parse_args(argv)
    levels = [float(v) for v in args.levels.split(",")]
    if args.samples < 1 or any(not (level >= 0) for level in levels):
        parser.error(f"--samples must be >= 1 and --levels >= 0, got {args.samples} and {levels}")
    vf = load_value_function(args.source).value_function
    system = vf.system
    states = sample_states(system, args.samples, args.seed)
    start = time.perf_counter()
    result = rollout(vf, states, progress=False)
    wall = time.perf_counter() - start
    value, collided = result.initial_value, result.collided
    false_safe = (value > 0) & collided
    print(f"# {args.source}: {args.samples} uniform states (seed {args.seed}), rollouts of its policy in {wall:.0f} s")
    print("| level | false safe % (V > level and collides) | box share with V > level |")
    print("|---:|---:|---:|")
    for level in levels:
        above = value > level
        share = 100 * float((above & collided).float().mean())
        print(f"| {level:g} | {share:.3f} | {float(above.float().mean()):.4f} |")
    if bool(false_safe.any()):
        q = torch.quantile(value[false_safe].double(), torch.tensor([0.1, 0.5, 0.9, 1.0], dtype=torch.float64))
        print(f"\n# V over the {int(false_safe.sum())} false-safe states: 10/50/90/100 % quantiles {q.tolist()}")
    if args.pairwise:
        union = pairwise_union_values(args.pairwise, system, states, system.horizon)
        capped = torch.minimum(value, union.to(value.dtype))
        share = 100 * float(((capped > 0) & collided).float().mean())
        print(f"# min(V, V_union) > 0 and collides (the same rollouts): {share:.3f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
