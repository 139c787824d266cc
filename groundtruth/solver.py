"""Level-set HJI solver in torch for systems with up to 4 state dimensions.

Scheme (as in the MATLAB level-set toolbox and hj_reachability): upwind HJ-WENO5 derivatives,
Lax-Friedrichs numerical Hamiltonian with the system's derived dissipation bounds, TVD-RK3 in time
with a CFL-limited step that lands exactly on every requested output time, and the system's kind
of problem as a variational inequality after each full step: ``V <- min(V, l)`` for the avoid and
reach tubes, ``V <- max(min(V, l), -g)`` for reach-avoid (:mod:`reach.systems.problem`).

Conventions (docs/concepts.md): ``t`` is time-to-go and ``V(x, 0) = l(x)``. The value solves
``max(dV/dt - H(x, grad V), V - l) = 0``, so the semi-discrete right-hand side is::

    dV/dt = H(x, (p+ + p-) / 2) + sum_i alpha_i (p+_i - p-_i) / 2

(the dissipation term adds ``alpha dx V_xx``-like diffusion, which is stable in the time-to-go
direction).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import time
from collections.abc import Callable, Sequence

import torch
from tqdm.auto import tqdm

from groundtruth.grid import Grid
from groundtruth.settings import SolverSettings
from groundtruth.solution import GridSolution
from groundtruth.weno import SCALE as WENO_SCALE
from groundtruth.weno import mean_and_half_jump
from reach.compiling import maybe_compile
from reach.malloc_thresholds import retained_heap
from reach.memory_check import require_memory
from reach.systems.arrays import TORCH
from reach.systems.base import ControlAffineSystem
from reach.systems.problem import require_finite_margin
from reach.systems.registry import make_system

MAX_DIM = 4
#: ``compile=None`` compiles on CPU only for at least this many node updates (nodes x RK3 steps):
#: torch.compile costs a fixed time once per new system or grid, and pays off only on large work; the
#: threshold lies between a solve that ran faster eager and one that ran faster compiled on a first run
#: (measured: docs/results/groundtruth.md, *When the solver compiles*).
COMPILE_MIN_NODE_UPDATES = 2e8


#: innermost grid dimensions shorter than this are differenced on a transposed copy (_rhs_factory)
SHORT_INNER_LINE = 24


def _rhs_factory(
    system: ControlAffineSystem, grid: Grid, cols: list[torch.Tensor], alpha: list[torch.Tensor]
) -> Callable[[torch.Tensor], torch.Tensor]:
    spacing = grid.spacing
    periodic = grid.periodic
    # mean_and_half_jump() returns WENO_SCALE * dx times the mean and the half jump of the one-sided
    # derivatives: the Hamiltonian takes the factor 1 / (WENO_SCALE dx) into its coefficients (no pass
    # over the grid), the dissipation into alpha
    unscale = [1.0 / (WENO_SCALE * dx) for dx in spacing]
    alpha = [a * k for a, k in zip(alpha, unscale)]
    hamiltonian = system.hamiltonian_at(cols, TORCH, scale=unscale, prune=True)
    # eager torch runs the WENO5 passes along the innermost dimension in rows of its length; below
    # SHORT_INNER_LINE nodes a transposed copy is cheaper, at longer lines it is not (measured:
    # docs/results/groundtruth.md, *Eager speed*)
    last_moved = grid.ndim - 1 if grid.ndim > 1 and grid.shape[-1] < SHORT_INNER_LINE else None

    def rhs(v: torch.Tensor) -> torch.Tensor:
        p_mean: list[torch.Tensor] = []
        dissipation: torch.Tensor | None = None
        for i in range(grid.ndim):
            if i == last_moved:  # differences along a short contiguous line: move it to the front
                mean, half_jump = mean_and_half_jump(v.movedim(i, 0).contiguous(), 0, spacing[i], periodic[i])
                mean, half_jump = mean.movedim(0, i), half_jump.movedim(0, i)
            else:
                mean, half_jump = mean_and_half_jump(v, i, spacing[i], periodic[i])
            p_mean.append(mean)
            dissipation = half_jump.mul_(alpha[i]) if dissipation is None else dissipation.addcmul_(alpha[i], half_jump)
        h = hamiltonian(p_mean)
        return dissipation.add_(h) if isinstance(h, torch.Tensor) and h.shape == dissipation.shape else dissipation + h

    return rhs


#: peak working memory of an eager solve, per grid node and state dimension, in float32, from the
#: largest measured (docs/results/groundtruth.md, *Memory of an eager solve*); float64 doubles it
BYTES_PER_NODE_AND_DIM = 110


def default_output_times(horizon: float, step: float = 0.1) -> list[float]:
    """Times-to-go ``0, step, 2 step, ..., horizon`` (evenly spaced, at most ``step`` apart).

    Stored from 0: rollouts and filters query every time-to-go down to 0, and a solution that
    stores only its horizon cannot serve them."""
    k = max(1, math.ceil(horizon / step - 1e-9))
    return [horizon * i / k for i in range(k + 1)]


def estimate_solve_bytes(shape: Sequence[int], num_times: int, dtype: torch.dtype = torch.float32) -> int:
    """Peak memory of a solve: working arrays plus the stored time slices (twice, while stacked)."""
    nodes = math.prod(shape)
    itemsize = torch.empty(0, dtype=dtype).element_size()
    return int(nodes * (BYTES_PER_NODE_AND_DIM * len(shape) * itemsize / 4 + 2 * num_times * itemsize))


def check_memory(shape: Sequence[int], num_times: int, dtype: torch.dtype = torch.float32) -> int:
    """Refuse, before allocating anything, a solve that needs more memory than the machine has."""
    what = f"a {'x'.join(map(str, shape))} grid with {num_times} stored times"
    return require_memory(estimate_solve_bytes(shape, num_times, dtype), what, "use a coarser grid or fewer --times")


def solve(
    system: ControlAffineSystem | str,
    grid: Grid | int | Sequence[int],
    times: Sequence[float],
    *,
    settings: SolverSettings | None = None,
    progress: bool = True,
) -> GridSolution:
    """Solve the value function of ``system``'s problem on ``grid`` and keep it at the given ``times``.

    The system's kind (:mod:`reach.systems.problem`) sets the problem: avoid (the BRT of its failure
    set), reach (the states that can reach its target within the time-to-go) or reach-avoid (reach
    the target while the constraint margin ``g`` stays positive); the Hamiltonian's game directions,
    the boundary value and the variational inequality follow from it.

    Args:
        system: any system with at most 4 state dimensions: an instance, a registered name or an
            import path ``package.module:ClassName``.
        grid: a :class:`Grid` (solved as given), or node counts (int or per dimension) over the
            system's domain; those are solved on whole nodes more where the system's training domain
            is wider (:meth:`Grid.widened`) and cut back to the domain's nodes.
        times: output times-to-go (>= 0, increasing); the last one is the horizon.
        settings: the scheme's accuracy and time-stepping options (:class:`SolverSettings`: CFL
            number, dissipation, tube, dtype, device, compilation); ``None``: the defaults.
        progress: show a tqdm bar over simulated time.
    """
    if settings is None:
        settings = SolverSettings()
    elif not isinstance(settings, SolverSettings):
        raise ValueError(f"settings must be a groundtruth.SolverSettings, got {settings!r}")
    cfl, dissipation, tube = settings.cfl, settings.dissipation, settings.tube
    dtype, device, compile = settings.dtype, settings.device, settings.compile
    system = make_system(system)
    if system.state_dim > MAX_DIM:
        raise ValueError(f"the grid solver handles at most {MAX_DIM} dimensions, {system.name} has {system.state_dim}")
    if isinstance(grid, Grid):
        asked, keep = grid, None
    else:  # over the domain, solved on the training domain where that is wider (Grid.widened)
        asked = Grid.for_system(system, grid)
        grid, keep = asked.widened(system.training_domain())
        keep = None if grid == asked else keep
    if grid.ndim != system.state_dim:
        raise ValueError(f"grid has {grid.ndim} dimensions, {system.name} has {system.state_dim}")
    out_times = [float(t) for t in times]
    if not out_times or any(not math.isfinite(t) or t < 0 for t in out_times):
        raise ValueError(f"times must be finite and >= 0, got {list(times)}")
    if any(b <= a for a, b in itertools.pairwise(out_times)):
        raise ValueError(f"times must be strictly increasing, got {out_times}")

    need = check_memory(grid.shape, len(out_times), dtype)

    start = time.perf_counter()
    cols = grid.columns(dtype, device)
    problem = system.problem
    target = torch.broadcast_to(system.terminal_margin_columns(cols, TORCH), grid.shape).contiguous()
    constraint = (
        torch.broadcast_to(system.constraint_margin_columns(cols, TORCH), grid.shape).contiguous()
        if problem.has_constraint
        else None
    )
    # a margin that is NaN or infinite at some node is named here, not found as NaN values after the solve
    require_finite_margin(system, problem.margin_method, target, cols)
    if constraint is not None:
        require_finite_margin(system, "constraint_margin_columns", constraint, cols)
    bounds = [torch.as_tensor(a, dtype=dtype, device=device) for a in system.dissipation_columns(cols, TORCH)]
    rate = sum(torch.broadcast_to(a, grid.shape) / dx for a, dx in zip(bounds, grid.spacing))
    max_rate = float(rate.max())
    if not math.isfinite(max_rate):
        raise ValueError(f"{system.name}: the dynamics (drift and input matrices) are NaN or infinite on the grid")
    dt_max = cfl / max_rate if max_rate > 0 else math.inf
    if dissipation == "global":
        bounds = [b.max() for b in bounds]
    rhs = _rhs_factory(system, grid, cols, bounds)

    def rk3(v: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        v1 = torch.addcmul(v, h, rhs(v))
        v2 = torch.addcmul(v1, h, rhs(v1)).mul_(0.25).add_(v, alpha=0.75)
        v3 = torch.addcmul(v2, h, rhs(v2)).mul_(2.0 / 3.0).add_(v, alpha=1.0 / 3.0)
        if tube == "set" and constraint is None:
            return v3
        return problem.enforce(v3, v if tube == "min_over_time" else floor, constraint)

    floor = target if tube == "min_with_target" else None  # min_over_time: V_old (<= l) is the floor

    if compile is None:
        updates = grid.num_points * math.ceil(out_times[-1] / dt_max) if math.isfinite(dt_max) else 0
        compile = None if torch.device(device).type == "cpu" and updates >= COMPILE_MIN_NODE_UPDATES else False
    # compile the right-hand side, not the whole RK3 step: the three stages reuse one graph, which
    # compiles faster and runs as fast (measured: docs/results/groundtruth.md, *When the solver compiles*)
    rhs = maybe_compile(rhs, compile, "solving")
    values = []
    steps = 0
    t = 0.0
    v = problem.boundary_value(target, constraint).clone()
    # on CPU, freed temporaries stay in the heap: page faults slowed eager solves (reach.malloc_thresholds)
    keep_heap = retained_heap(need) if torch.device(device).type == "cpu" else contextlib.nullcontext()
    with (
        keep_heap,
        # nothing here is differentiated, so the Hamiltonian may accumulate in place, and inference mode
        # skips the version counters and view records of the ~70 tensor calls per dimension and stage;
        # the stored slices are stacked outside it, so the solution's values are ordinary tensors
        torch.inference_mode(),
        tqdm(
            total=out_times[-1],
            desc=f"{system.name} {'x'.join(map(str, grid.shape))}",
            unit="s",
            **({} if progress else {"disable": True}),
            bar_format="{l_bar}{bar}| {n:.3f}/{total:.3f} s [{elapsed}<{remaining}]",
        ) as bar,
    ):
        for t_out in out_times:
            while t < t_out:
                # The last step to an output time is shortened to land on it exactly; a remainder
                # below 1e-12 s is round-off and is absorbed into the previous step.
                h = t_out - t if t_out - t <= dt_max * (1 + 1e-9) else dt_max
                v = rk3(v, torch.tensor(h, dtype=dtype, device=device))  # a tensor: no recompiles
                t = t_out if h == t_out - t else t + h
                steps += 1
                bar.update(h)
            values.append(v.clone())
    wall = time.perf_counter() - start
    return GridSolution(
        system=system,
        grid=asked,
        times=torch.tensor(out_times, dtype=torch.float64),
        values=torch.stack(values if keep is None else [v[keep] for v in values]).cpu(),
        metadata={
            "scheme": {
                "spatial": "HJ-WENO5 (Jiang-Peng), upwind",
                "hamiltonian": f"Lax-Friedrichs, {dissipation} dissipation",
                "time": "TVD-RK3",
                "cfl": cfl,
                "dt": dt_max,
                "steps": steps,
                "tube": tube,
                "kind": problem.name,
                "boundary": "periodic or extrapolate away from zero",
                "compiled": compile is not False,  # torch.compile asked for (it falls back to eager on failure)
                # the nodes solved on, where the system's training domain widened them (Grid.widened)
                **({} if keep is None else {"solved_on": {"low": grid.low, "high": grid.high, "shape": grid.shape}}),
            },
            "dtype": str(dtype).replace("torch.", ""),
            "device": str(device),
            "wall_time_s": wall,
        },
    )
