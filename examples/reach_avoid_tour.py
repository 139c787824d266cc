"""A reach-avoid system defined outside the package, through every tool, from Python.

``examples/my_systems.py`` declares ``DubinsGap`` (a Dubins car that must reach a goal disc through
the gap between two round obstacles, against the wind): its physics, ``kind = "reach-avoid"``, a
target margin and a constraint margin. This script takes it through the grid solver, training,
verification, its environment under a safety filter, and a small sweep, and reloads the trained
run in a new process. docs/custom_system.md shows the same steps from the command line.

Run from the repository root: ``PYTHONPATH=examples python examples/reach_avoid_tour.py [OUT]``
(default OUT: runs/tutorial/gap-python). ``--tiny`` runs everything at toy size (the tests do).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import torch
from my_systems import DubinsGap

import reach_envs  # noqa: F401  (registers Reach-v0)
from groundtruth import solve
from safety import SafetyFilterWrapper, load_value_function
from safety.verification.verify import VerifySettings, sample_states, verify
from studies.sweeps import SweepSpec, run_sweep
from training import TrainConfig, Trainer
from training.accuracy import ReferenceEvaluator


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default="runs/tutorial/gap-python")
    parser.add_argument("--tiny", action="store_true", help="toy sizes: seconds, not minutes")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tiny = args.tiny
    system = DubinsGap()

    # 1. the grid: V(x, t) <= 0 where the goal can be reached within t, whatever the wind does
    times = [0.25 * k for k in range(7)]  # to the 1.5 s horizon
    grid = solve(system, 21 if tiny else 51, times, progress=False)
    grid.save(out / "gap_gt.npz")
    inside = float((grid.values[-1] <= 0).float().mean())
    print(f"grid: {grid.values.shape[1:]} nodes, reach-avoid set {inside:.1%} of the domain at t = 1.5 s")

    # 2. training: the residual is the kind's (brat_hjivi); the exact parameterisation holds max(l, -g)
    config = TrainConfig(
        system=system, steps=20 if tiny else 1000, layout="ssl" if tiny else "ssssl", width=16 if tiny else 128
    )
    if tiny:
        config.points, config.compile = 256, False
    run = out / "gap"
    Trainer(config.validate(), run, progress=False).train()
    vf = load_value_function(str(run)).value_function
    print("accuracy against the grid at t = 1.5:", ReferenceEvaluator(grid, 1.5)(vf))

    # 3. verification: rollouts of the learned policy; the scenario set {V < -delta}
    settings = VerifySettings(samples=300 if tiny else 20000, scenario_samples=100 if tiny else 20000, robust_samples=0)
    row = verify(vf, sample_states(system, settings.samples, 0), settings, progress=False)
    print(
        f"verification: false reachable {row['false_reachable_rate']:.2%}, failures {row['failure_rate']:.2%}, "
        f"delta {row['delta']:.3f}, scenario set {row['scenario_volume']:.3f} of the domain, eps {row['eps']:.2e}"
    )

    # 4. the environment under a safety filter: keep the task feasible, the deadline counting down
    env = SafetyFilterWrapper(gym.make("Reach-v0", system=system, disturbance="pursue"), grid, kind="switch")
    env.reset(seed=0, options={"state": [-0.2, 0.0, 0.0]})  # before the gap, facing the goal
    done = False
    while not done:
        _, reward, terminated, truncated, info = env.step(torch.zeros(1).numpy())  # nominal: drive straight
        done = terminated or truncated
    print(f"filtered episode: {info['outcome']} at t = {info['time']:.2f} s, reward {reward}")

    # 5. a small sweep: each layout trained and scored against the grid
    spec = SweepSpec(
        system=system,
        layouts=["ssl", "rsl"] if tiny else ["ssssl", "rrrsl"],
        seeds=[0],
        budget_s=None,
        steps=10 if tiny else 300,
        snapshots=1,
        width=16 if tiny else 64,
        grid=21 if tiny else 31,
        train={"points": 256, "compile": False} if tiny else {},
    )
    report, failed = run_sweep(spec, out / "gap_sweep", progress=False)
    print(f"sweep: {report} ({len(failed)} failed)")

    # 6. the run reloads in a new process
    code = (
        "from safety import load_value_function; import my_systems;"
        f"vf = load_value_function({str(run)!r}).value_function; print(vf.system.kind, vf.system.reference())"
    )
    reloaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    print("reloaded in a new process:", reloaded.strip())


if __name__ == "__main__":
    main()
