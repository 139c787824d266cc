"""``reach groundtruth``: solve a low-dimensional system's BRT on a grid (level-set method)."""

from __future__ import annotations

import argparse
import itertools
from typing import Any

import torch

from groundtruth.grid import Grid
from groundtruth.settings import DISSIPATIONS, SolverSettings
from groundtruth.solver import MAX_DIM, check_memory, default_output_times, solve
from reach.systems import make_system
from reach.validation import (
    check_int,
    check_output_path,
    csv_floats,
    csv_items,
    device_arg,
    positive_float_arg,
)
from reach_cli.options import add_subparser, signature_default

#: the --dtype choices
DTYPES = {"float32": torch.float32, "float64": torch.float64}


def add_parser(sub: Any) -> None:
    p = add_subparser(sub, "groundtruth", help="solve a low-dimensional system's BRT on a grid (level-set method)")
    p.add_argument(
        "system",
        help="system: a registered name or package.module:ClassName, e.g. air3d, relativepair, my_pkg.dynamics:Dubins",
    )
    p.add_argument("--grid", default="101", help="nodes per dimension, e.g. 101 or 101,101,51")
    p.add_argument("--horizon", type=positive_float_arg, default=None, help="final time-to-go (default: the system's)")
    p.add_argument(
        "--times",
        default=None,
        help="comma-separated output times, e.g. 0.5,1.0 or 0,0.05,...,1.1 (default: every 0.1 s from 0 to the "
        "horizon, which rollouts and filters need)",
    )
    p.add_argument(
        "--cfl",
        type=positive_float_arg,
        default=None,
        help=f"Courant number (default {signature_default(SolverSettings, 'cfl')})",
    )
    p.add_argument(
        "--dissipation",
        choices=list(DISSIPATIONS),
        default=None,
        help=f"Lax-Friedrichs dissipation (default {signature_default(SolverSettings, 'dissipation')})",
    )
    p.add_argument(
        "--dtype",
        choices=list(DTYPES),
        default=None,
        help=f"default {str(signature_default(SolverSettings, 'dtype')).replace('torch.', '')}",
    )
    p.add_argument(
        "--device",
        type=device_arg,
        default=None,
        help=f"cpu or cuda (default {signature_default(SolverSettings, 'device')})",
    )
    p.add_argument(
        "--compile",
        choices=["auto", "on", "off"],
        default="auto",
        help="torch.compile the solver step (auto: on CPU from 2e8 node updates, eager on GPUs)",
    )
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--plot", default=None, help="also draw zero-level slices to this PNG")
    p.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace) -> SolverSettings:
    """The solver settings the options ask for; an option left out keeps :class:`SolverSettings`' default."""
    options = {
        "cfl": args.cfl,
        "dissipation": args.dissipation,
        "dtype": DTYPES[args.dtype] if args.dtype else None,
        "device": args.device,
        "compile": None if args.compile == "auto" else args.compile == "on",
    }
    return SolverSettings(**{k: v for k, v in options.items() if v is not None})


def parse_grid(text: str, ndim: int) -> int | list[int]:
    """``"101"`` or ``"101,101,51"``: node counts, each checked (the solver needs at least 5)."""
    parts = csv_items("--grid", text)
    try:
        counts = [int(v) for v in parts]
    except ValueError:
        raise ValueError(f"--grid must be node counts like 101 or 101,101,51, got {text!r}") from None
    if len(counts) not in (1, ndim):
        raise ValueError(f"--grid needs 1 or {ndim} node counts for a {ndim}D system, got {text!r}")
    for count in counts:
        check_int("--grid", count, 5)
    return counts[0] if len(counts) == 1 else counts


def run(args: argparse.Namespace) -> int:
    from groundtruth.plotting import plot_zero_level_slices  # lazy: plotting only when this command runs

    # everything is checked before the solve: system, grid, times, memory, output paths
    system = make_system(args.system)
    if system.state_dim > MAX_DIM:
        raise ValueError(f"the grid solver handles at most {MAX_DIM} dimensions; {system.name} has {system.state_dim}")
    horizon = args.horizon if args.horizon is not None else system.horizon
    if args.times:
        times = csv_floats("--times", args.times)
        if any(t < 0 for t in times) or any(b <= a for a, b in itertools.pairwise(times)):
            raise ValueError(f"--times must be increasing and >= 0, got {times}")
        if any(t > horizon + 1e-12 for t in times):
            raise ValueError(f"--times {times} go beyond --horizon {horizon}")
        if abs(times[-1] - horizon) > 1e-12:
            times.append(horizon)
    else:
        times = default_output_times(horizon)
    grid = parse_grid(args.grid, system.state_dim)
    settings = settings_from_args(args)
    check_memory(Grid.for_system(system, grid).shape, len(times), settings.dtype)
    check_output_path(args.out, "--out")
    if args.plot:
        check_output_path(args.plot, "--plot")
    solution = solve(system, grid, times, settings=settings)
    path = solution.save(args.out)
    scheme = solution.metadata["scheme"]
    print(
        f"wrote {path}: {system.name} on {'x'.join(map(str, solution.grid.shape))}, "
        f"{len(times)} times from {times[0]:g} to {times[-1]:g}, {scheme['steps']} steps, "
        f"{solution.metadata['wall_time_s']:.1f} s"
    )
    if args.plot:
        print(f"wrote {plot_zero_level_slices(solution, args.plot)}")
    return 0
