"""Reach rollouts with and without the target floor's early exit: the work and wall time it saves,
and that every outcome is the same.

Run: ``python benchmarks/bench_reach_exit.py`` (``--sources pretrained:dubins3d
pretrained:dubinsreachavoid --states 50000 --threads 2``).

A reach rollout stops a trajectory once its target is out of reach in the time left
(:meth:`reach.systems.base.ControlAffineSystem.target_floor`; a reach-avoid one only where its
constraint is out of reach too). For each source the script rolls out the same uniform states
(``--seed``) under the card's protocol (explicit Euler, ``dt = 0.0025``, the gradient policy), once
simulating every step (``early_exit=False``) and once with the exits, in one process, one after the
other, and prints the wall time, the share of state-steps evaluated and how many outcomes
(reached, violated, reach and violation times) differ. Time it on a quiet machine.
"""

from __future__ import annotations

import argparse
import time

import torch

from safety.value_loading import load_value_function
from safety.verification.rollout import rollout
from safety.verification.verify import sample_states


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sources", nargs="+", default=["pretrained:dubins3d", "pretrained:dubinsreachavoid"])
    parser.add_argument("--states", type=int, default=50_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dt", type=float, default=0.0025)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"{args.states} states, dt {args.dt}, {args.threads} torch threads, torch {torch.__version__}")
    print("| source | early exit | wall (s) | state-steps evaluated | outcomes that differ |")
    print("|---|---|---:|---:|---:|")
    for source in args.sources:
        vf = load_value_function(source).value_function
        system = vf.system
        if not system.problem.reaches:
            raise SystemExit(f"{source} is a {system.kind} model; the target floor exits reach kinds")
        x = sample_states(system, args.states, args.seed)
        runs = {}
        for exit_early in (False, True):
            start = time.perf_counter()
            runs[exit_early] = rollout(vf, x, dt=args.dt, early_exit=exit_early, progress=False)
            runs[exit_early].wall_time = time.perf_counter() - start
        full = runs[False]
        for exit_early, r in runs.items():
            differ = (
                (r.reached != full.reached)
                | (r.collided != full.collided)
                | ~torch.isclose(r.reach_time, full.reach_time, equal_nan=True)
                | ~torch.isclose(r.collision_time, full.collision_time, equal_nan=True)
            )
            print(
                f"| {source} | {'yes' if exit_early else 'no'} | {r.wall_time:.1f} | "
                f"{r.state_steps:,} ({100 * r.work_fraction:.0f} %) | {int(differ.sum())} |"
            )


if __name__ == "__main__":
    main()
