"""The grid solver's reach and reach-avoid problems against hj_reachability (JAX), value for value.

Run: ``python benchmarks/hj_kinds.py`` (``--grid 51`` for a quick look; ``--hj-python PATH`` to use
an interpreter that already has hj_reachability, otherwise one is installed for this benchmark only,
as ``benchmarks/hj_comparison.py`` does).

Two problems, each solved by both on the same nodes with the same scheme (HJ-WENO5, local
Lax-Friedrichs, TVD-RK3, float32) from the boundary value to the horizon:

- DeepReach's Dubins3D in reach mode (``reach.systems.Dubins3D("reach")``): the control minimises;
  hj_reachability keeps the tube with ``backwards_reachable_tube``, reach with ``V <- min(V, l)``;
- the reach-avoid car (``reach.systems.DubinsReachAvoid``): the control minimises and the wind
  maximises; hj_reachability applies the reach-avoid variational inequality as its value
  postprocessor, ``V <- max(min(V, l), -g)`` after each step, from ``max(l, -g)``, written here
  independently of reach's.

It prints, per problem, the IoU of the two solvers' ``{V <= 0}`` and the largest ``|dV|`` where
``|V| < 0.05`` (near the zero level), with each solve's wall time. The issue's goals at 101^3: IoU
>= 0.99 and max ``|dV|`` near the zero level <= 2e-3.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from hj_venv import hj_python  # benchmarks/hj_venv.py: the interpreter with hj_reachability

ROOT = Path(__file__).resolve().parents[1]
#: (label, reach system, hj problem key, horizon)
CASES = (
    ("Dubins3D, reach", "dubins3d", "dubins3d_reach", 1.0),
    ("DubinsReachAvoid", "dubinsreachavoid", "dubins_reach_avoid", 2.0),
)
#: the band around the zero level where values are compared
NEAR = 0.05

REACH_CHILD = r"""
import json, sys, time
sys.path.insert(0, sys.argv[4])
import numpy as np
from groundtruth import solve
from reach.systems import make_system
system = make_system(sys.argv[1])
t0 = time.perf_counter()
sol = solve(system, int(sys.argv[2]), [0.0, float(sys.argv[3])], progress=False)
np.save(sys.argv[5], sol.values[-1].numpy())
print(json.dumps({"solve_s": time.perf_counter() - t0}))
"""

# The two problems in hj_reachability's terms, restated from their definitions (docs/concepts.md):
# the same dynamics, boxes, domains, margins and variational inequalities as reach.systems.dubins.
HJ_CHILD = r"""
import json, sys, time
import jax.numpy as jnp
import numpy as np
import hj_reachability as hj
from hj_reachability import dynamics as hjd, sets

class Dubins(hjd.ControlAndDisturbanceAffineDynamics):
    def __init__(self, speed, turn, wind):
        super().__init__("min", "max", sets.Box(jnp.array([-turn]), jnp.array([turn])),
                         sets.Box(jnp.array([-wind, -wind]), jnp.array([wind, wind])))
        self.speed = speed
    def open_loop_dynamics(self, x, t):
        return jnp.array([self.speed * jnp.cos(x[2]), self.speed * jnp.sin(x[2]), 0.0])
    def control_jacobian(self, x, t):
        return jnp.array([[0.0], [0.0], [1.0]])
    def disturbance_jacobian(self, x, t):
        return jnp.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])

def disc(s, cx, cy, r):
    return jnp.sqrt((s[..., 0] - cx) ** 2 + (s[..., 1] - cy) ** 2) - r

key, n, horizon = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
grid = hj.Grid.from_lattice_parameters_and_boundary_conditions(
    sets.Box(jnp.array([-1.0, -1.0, -np.pi]), jnp.array([1.0, 1.0, np.pi])), (n, n, n), periodic_dims=2)
if key == "dubins3d_reach":
    dynamics = Dubins(0.6, 1.1, 0.0)
    l = disc(grid.states, 0.0, 0.0, 0.25)
    settings = hj.SolverSettings.with_accuracy(
        "very_high", hamiltonian_postprocessor=hj.solver.backwards_reachable_tube)
    start = l
else:
    dynamics = Dubins(0.6, 1.1, 0.1)
    l = disc(grid.states, 0.7, 0.0, 0.2)
    g = disc(grid.states, 0.1, 0.0, 0.25)
    settings = hj.SolverSettings.with_accuracy(
        "very_high", value_postprocessor=lambda t, v: jnp.maximum(jnp.minimum(v, l), -g))
    start = jnp.maximum(l, -g)
t0 = time.perf_counter()
values = hj.solve(settings, dynamics, grid, jnp.array([0.0, -horizon]), start, progress_bar=False)
values.block_until_ready()
np.save(sys.argv[5], np.asarray(values[-1]))
print(json.dumps({"solve_s": time.perf_counter() - t0}))
"""


def run(python: str, child: str, key: str, n: int, horizon: float) -> tuple[np.ndarray, float]:
    """One solve in a fresh process: its values at the horizon and its solve time."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "v.npy"
        done = subprocess.run(
            [python, "-c", child, key, str(n), str(horizon), str(ROOT), str(out)], capture_output=True, text=True
        )
        if done.returncode:
            raise RuntimeError(f"{key} {n}: {done.stderr[-2000:]}")
        return np.load(out), json.loads(done.stdout.strip().splitlines()[-1])["solve_s"]


def compare(reach_v: np.ndarray, hj_v: np.ndarray) -> dict[str, float]:
    """IoU of the two ``{V <= 0}`` and the largest ``|dV|`` near the zero level."""
    a, b = reach_v <= 0, hj_v <= 0
    near = (np.abs(hj_v) < NEAR) | (np.abs(reach_v) < NEAR)
    return {
        "iou": float((a & b).sum() / max(1, (a | b).sum())),
        "max_dv_near_zero": float(np.abs(reach_v - hj_v)[near].max()),
        "max_dv": float(np.abs(reach_v - hj_v).max()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=int, default=101, help="nodes per dimension (default 101)")
    parser.add_argument("--hj-python", default=None, help="an interpreter that has hj_reachability")
    args = parser.parse_args(argv)
    python = hj_python(args.hj_python)
    print(f"| problem | grid | BRT IoU | max abs dV, abs V < {NEAR} | max abs dV | reach solve (s) | hj solve (s) |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for label, system, key, horizon in CASES:
        reach_v, reach_s = run(sys.executable, REACH_CHILD, system, args.grid, horizon)
        hj_v, hj_s = run(python, HJ_CHILD, key, args.grid, horizon)
        c = compare(reach_v, hj_v)
        print(
            f"| {label} | {args.grid}^3 | {c['iou']:.4f} | {c['max_dv_near_zero']:.2e} | {c['max_dv']:.2e} "
            f"| {reach_s:.1f} | {hj_s:.1f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
