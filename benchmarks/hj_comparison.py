"""The grid solver against hj_reachability (JAX) on the same systems, grids and horizons.

Run: ``python benchmarks/bench_groundtruth.py --against hj_reachability`` (``--quick`` for two small
cases; ``--hj-python PATH`` to use an interpreter that already has hj_reachability).

Every solve is a fresh process, timed from the parent with interpreter start-up and imports
included, as a user meets it:

- ``reach`` first run: an empty torch inductor cache (a new or changed system); second run: the
  same cache again (``groundtruth.solve`` defaults, so compiling only where its rule says so).
- ``reach groundtruth`` (the command line, ``python -m reach``, as the console script runs it),
  first and second run the same way, with ``--threads`` all cores (what torch gives a script; the
  command's own default counts the cores other processes leave free) and
  writing its ``.npz`` as the command always does.
- hj_reachability first and second run: JAX keeps no compile cache between processes by default,
  so both compile; the second shows the spread.

Each size runs ``repeats`` rounds (``--repeats``, default 3). A round runs every solver's first run,
then every solver's second run, so that a shared machine's slow moments fall on all of them alike.
Times are medians over the rounds, and each ratio is the median of the rounds' own ratios (reach's
run over the hj_reachability run of the same round and slot). On this 2-core VM one solve's time
varies by up to 1.7x between minutes, as much as the gap a single round tries to measure.

A size meets its goal when the script's and the command's median ratios all do.

The two solvers run the same scheme (HJ-WENO5, local Lax-Friedrichs, TVD-RK3, CFL 0.75, float32)
on the same nodes, from ``l`` at time-to-go 0 to the horizon; hj_reachability freezes the value
where the Hamiltonian would lower it past zero (``backwards_reachable_tube``), reach takes
``min(V, l)``: the same BRT. The table reports the IoU of the two BRTs, so a mismatch in the
systems' definitions shows.

hj_reachability is installed only for this benchmark, in a virtual environment of its own
(``~/.cache/reach-bench/hj-venv`` unless ``--hj-python`` is given); it is never a dependency.
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
from hj_venv import hj_python  # benchmarks/hj_venv.py: the interpreter with hj_reachability

ROOT = Path(__file__).resolve().parents[1]

#: (label, reach system, hj system key, grid sizes, horizon)
CASES = (
    ("Air3D", "air3d", "air3d", (31, 51, 71, 101), 1.0),
    ("DubinsAvoid (3D, user-defined)", "my_systems:DubinsAvoid", "dubins_avoid", (51,), 1.0),
    ("DubinsAccel (4D, user-defined)", "my_systems:DubinsAccel", "dubins_accel", (21, 31, 41), 1.0),
)
QUICK_CASES = (
    ("Air3D", "air3d", "air3d", (31,), 1.0),
    ("DubinsAccel (4D, user-defined)", "my_systems:DubinsAccel", "dubins_accel", (21,), 1.0),
)

REACH_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
sys.path.insert(0, sys.argv[4])
import numpy as np
from groundtruth import solve
from reach.systems import make_system
system = make_system(sys.argv[1])
t1 = time.perf_counter()
sol = solve(system, int(sys.argv[2]), [0.0, float(sys.argv[3])], progress=False)
t2 = time.perf_counter()
np.save(sys.argv[5], sol.values[-1].numpy())
print(json.dumps({"import_s": t1 - t0, "solve_s": t2 - t1, "compiled": sol.metadata["scheme"]["compiled"],
                  "steps": sol.metadata["scheme"]["steps"]}))
"""

# The three systems in hj_reachability's terms: the same dynamics, input boxes, domains and
# failure sets as reach.systems.Air3D and examples/my_systems.py (checked by the BRT IoU).
HJ_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import jax.numpy as jnp
import numpy as np
import hj_reachability as hj
from hj_reachability import dynamics as hjd, sets

class Air3D(hjd.ControlAndDisturbanceAffineDynamics):
    def __init__(self):
        super().__init__("max", "min", sets.Box(jnp.array([-3.0]), jnp.array([3.0])),
                         sets.Box(jnp.array([-3.0]), jnp.array([3.0])))
    def open_loop_dynamics(self, x, t):
        return jnp.array([-0.75 + 0.75 * jnp.cos(x[2]), 0.75 * jnp.sin(x[2]), 0.0])
    def control_jacobian(self, x, t):
        return jnp.array([[x[1]], [-x[0]], [-1.0]])
    def disturbance_jacobian(self, x, t):
        return jnp.array([[0.0], [0.0], [1.0]])

class DubinsAvoid(hjd.ControlAndDisturbanceAffineDynamics):
    def __init__(self):
        super().__init__("max", "min", sets.Box(jnp.array([-1.5]), jnp.array([1.5])),
                         sets.Box(jnp.array([-0.1, -0.1]), jnp.array([0.1, 0.1])))
    def open_loop_dynamics(self, x, t):
        return jnp.array([0.8 * jnp.cos(x[2]), 0.8 * jnp.sin(x[2]), 0.0])
    def control_jacobian(self, x, t):
        return jnp.array([[0.0], [0.0], [1.0]])
    def disturbance_jacobian(self, x, t):
        return jnp.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])

class DubinsAccel(hjd.ControlAndDisturbanceAffineDynamics):
    def __init__(self):
        super().__init__("max", "min", sets.Box(jnp.array([-1.5, -1.0]), jnp.array([1.5, 1.0])),
                         sets.Box(jnp.array([-0.05, -0.05]), jnp.array([0.05, 0.05])))
    def open_loop_dynamics(self, x, t):
        return jnp.array([x[3] * jnp.cos(x[2]), x[3] * jnp.sin(x[2]), 0.0, 0.0])
    def control_jacobian(self, x, t):
        return jnp.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    def disturbance_jacobian(self, x, t):
        return jnp.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0], [0.0, 0.0]])

SYSTEMS = {
    "air3d": (Air3D, [-1.0, -1.0, -np.pi], [1.0, 1.0, np.pi], 2,
              lambda s: jnp.hypot(s[..., 0], s[..., 1]) - 0.25),
    "dubins_avoid": (DubinsAvoid, [-1.5, -1.5, -np.pi], [1.5, 1.5, np.pi], 2,
                     lambda s: jnp.sqrt((s[..., 0] - 0.3) ** 2 + (s[..., 1] - 0.2) ** 2) - 0.4),
    "dubins_accel": (DubinsAccel, [-1.5, -1.5, -np.pi, 0.0], [1.5, 1.5, np.pi, 1.2], 2,
                     lambda s: jnp.sqrt(s[..., 0] ** 2 + s[..., 1] ** 2) - 0.4),
}
make, lo, hi, periodic, margin = SYSTEMS[sys.argv[1]]
n, horizon = int(sys.argv[2]), float(sys.argv[3])
grid = hj.Grid.from_lattice_parameters_and_boundary_conditions(
    sets.Box(jnp.array(lo), jnp.array(hi)), (n,) * len(lo), periodic_dims=periodic)
settings = hj.SolverSettings.with_accuracy("very_high", hamiltonian_postprocessor=hj.solver.backwards_reachable_tube)
l = margin(grid.states)
t1 = time.perf_counter()
values = hj.solve(settings, make(), grid, jnp.array([0.0, -horizon]), l, progress_bar=False)
values.block_until_ready()
t2 = time.perf_counter()
np.save(sys.argv[5], np.asarray(values[-1]))
print(json.dumps({"import_s": t1 - t0, "solve_s": t2 - t1}))
"""


def _timed(argv: list[str], env: dict[str, str], what: str) -> tuple[subprocess.CompletedProcess[str], float]:
    """Run ``argv`` in a fresh process; its result and the parent's wall time (``what`` names it in
    the error a failed run raises)."""
    start = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    if done.returncode:
        raise RuntimeError(f"{what} failed:\n{done.stderr[-2000:]}")
    return done, wall


def one_round(runs: dict[str, Callable[[dict[str, str]], dict]], base_env: dict[str, str]) -> dict[str, list[dict]]:
    """A first and a second run of each of ``runs`` (name -> ``run(env)``), interleaved so that the
    machine's drift hits every solver alike: all first runs, then all second runs. Each runner has its
    own torch inductor cache, empty at its first run."""
    with contextlib.ExitStack() as stack:
        envs = {
            name: {**base_env, "TORCHINDUCTOR_CACHE_DIR": stack.enter_context(tempfile.TemporaryDirectory())}
            for name in runs
        }
        results: dict[str, list[dict]] = {name: [] for name in runs}
        for _ in range(2):
            for name, run in runs.items():
                results[name].append(run(envs[name]))
    return results


def run_command(system: str, n: int, horizon: float, env: dict[str, str]) -> dict:
    """One ``reach groundtruth`` in a fresh process; returns the parent's wall time and the values."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "solution.npz"
        argv = [sys.executable, "-m", "reach", "groundtruth", system, "--grid", str(n), "--horizon", str(horizon)]
        argv += ["--times", str(horizon), "--threads", str(os.cpu_count() or 1), "--out", str(out)]
        env = {**env, "PYTHONPATH": os.pathsep.join([str(ROOT / "examples"), env.get("PYTHONPATH", "")])}
        _, wall = _timed(argv, env, f"{system} {n}: reach groundtruth")
        with np.load(out) as data:
            values = data["values"][-1]
    return {"wall_s": wall, "values": values}


def run_child(python: str, code: str, system: str, n: int, horizon: float, env: dict[str, str]) -> dict:
    """One solve in a fresh process; returns its own timings, the parent's wall time and the values."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "values.npy"
        argv = [python, "-c", code, system, str(n), str(horizon), str(ROOT / "examples"), str(out)]
        done, wall = _timed(argv, env, f"{system} {n}: child")
        result = json.loads(done.stdout.strip().splitlines()[-1])
        result.update(wall_s=wall, values=np.load(out))
    return result


#: issue 23's goals: never slower than hj_reachability, and at most half its time at 101^3 and in 4D
GOAL_EVERYWHERE = 1.0
GOAL_LARGE = 0.5


def goal_ratio(n: int, dims: int) -> float:
    """The largest time ratio reach / hj_reachability the goals allow for an ``n^dims`` grid."""
    return GOAL_LARGE if dims >= 4 or n >= 101 else GOAL_EVERYWHERE


def brt_iou(a: np.ndarray, b: np.ndarray) -> float:
    inside_a, inside_b = a <= 0, b <= 0
    union = (inside_a | inside_b).sum()
    return float((inside_a & inside_b).sum() / union) if union else 1.0


Rounds = list[dict[str, list[dict]]]


def median_wall(rounds: Rounds, name: str, slot: int) -> float:
    """The median wall time of ``name``'s first (``slot`` 0) or second (1) runs over the rounds."""
    return statistics.median(r[name][slot]["wall_s"] for r in rounds)


def median_ratio(rounds: Rounds, name: str, slot: int) -> float:
    """The median over the rounds of ``name``'s wall time over hj_reachability's in the same slot."""
    return statistics.median(r[name][slot]["wall_s"] / r["hj"][slot]["wall_s"] for r in rounds)


def median_of(rounds: Rounds, name: str, key: str) -> float:
    """The median of a second run's own timing ``key`` (start-up or solve) over the rounds."""
    return statistics.median(r[name][1][key] for r in rounds)


def compare(quick: bool, hj_python_path: str | None, sizes: list[int] | None = None, repeats: int = 3) -> int:
    """Print the ratio table. Each size runs ``repeats`` rounds (:func:`one_round`); a time is the
    median over the rounds and a ratio the median of the rounds' own ratios (reach's run over the
    hj_reachability run beside it), so one slow moment of a shared machine does not decide a goal."""
    import platform

    import torch

    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    python = hj_python(hj_python_path)
    hj_version = subprocess.run(
        [python, "-c", "import hj_reachability, jax; print(hj_reachability.__version__, jax.__version__)"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    print(
        f"# Grid solver against hj_reachability {hj_version[0]} (jax {hj_version[1]}): fresh processes, "
        f"start-up included; python {platform.python_version()}, torch {torch.__version__}, {os.cpu_count()} CPUs; "
        f"{repeats} interleaved round(s) per size, medians\n"
    )
    print(
        "| system | grid | hj first s | hj second s | reach first s | reach second s | reach mode "
        "| first ratio | second ratio | command first s | command second s | command ratios | goal "
        "| hj start-up + solve s | reach start-up + solve s | BRT IoU |"
    )
    print("|---|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---|---:|---:|---:|")
    base_env = {**os.environ, "TQDM_DISABLE": "1", "PYTHONPATH": str(ROOT)}
    worst = 0.0
    missed: list[str] = []
    for label, system, hj_key, grids, horizon in QUICK_CASES if quick else CASES:
        for n in (m for m in grids if sizes is None or m in sizes):
            runs = {
                "hj": partial(run_child, python, HJ_CHILD, hj_key, n, horizon),
                "reach": partial(run_child, sys.executable, REACH_CHILD, system, n, horizon),
                "command": partial(run_command, system, n, horizon),
            }
            rounds = [one_round(runs, base_env) for _ in range(repeats)]
            hj0, reach0, command0 = rounds[0]["hj"][0], rounds[0]["reach"][0], rounds[0]["command"][0]
            if brt_iou(command0["values"], reach0["values"]) < 0.9999:
                raise RuntimeError(f"{label} {n}: reach groundtruth and groundtruth.solve found different BRTs")

            first, second = median_ratio(rounds, "reach", 0), median_ratio(rounds, "reach", 1)
            command = [median_ratio(rounds, "command", 0), median_ratio(rounds, "command", 1)]
            worst = max(worst, first, second, *command)
            dims = len(hj0["values"].shape)
            goal = goal_ratio(n, dims)
            met = max(first, second, *command) <= goal
            if not met:
                missed.append(f"{label} {n}^{dims}")
            print(
                f"| {label} | {n}^{dims} | {median_wall(rounds, 'hj', 0):.1f} | {median_wall(rounds, 'hj', 1):.1f} | "
                f"{median_wall(rounds, 'reach', 0):.1f} | {median_wall(rounds, 'reach', 1):.1f} | "
                f"{'compiled' if reach0['compiled'] else 'eager'} | {first:.2f} | {second:.2f} | "
                f"{median_wall(rounds, 'command', 0):.1f} | {median_wall(rounds, 'command', 1):.1f} | "
                f"{command[0]:.2f} / {command[1]:.2f} | <= {goal} {'met' if met else 'MISSED'} | "
                f"{median_of(rounds, 'hj', 'import_s'):.1f} + {median_of(rounds, 'hj', 'solve_s'):.1f} | "
                f"{median_of(rounds, 'reach', 'import_s'):.1f} + {median_of(rounds, 'reach', 'solve_s'):.1f} | "
                f"{brt_iou(hj0['values'], reach0['values']):.4f} |",
                flush=True,
            )
    print(f"\n# worst ratio reach / hj_reachability: {worst:.2f} (ratio < 1: reach is faster)")
    print(
        f"# goals (<= {GOAL_EVERYWHERE} everywhere, <= {GOAL_LARGE} at 101^3 and in 4D): "
        + (f"missed at {', '.join(missed)}" if missed else "met at every size")
    )
    return 0
