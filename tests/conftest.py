"""Shared test settings: headless plotting, no progress bars, float64 helpers."""

from __future__ import annotations

import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("TQDM_DISABLE", "1")

import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture(scope="session")
def air3d_grid():
    """An Air3D grid solution (51^3, 23 times over the 1.1 s horizon), solved once per session (~8 s)."""
    from groundtruth.solver import solve
    from reach.systems import Air3D

    times = [round(1.1 * k / 22, 6) for k in range(23)]
    sol = solve(Air3D(), 51, times, compile=False, progress=False)
    sol.outside = "clamp"
    return sol


@pytest.fixture(scope="session")
def pair_grid():
    """The 9D system's cooperative two-car problem on a coarse 45^3 grid (11 times), ~3 s."""
    from groundtruth.pairwise import solve_pairs
    from reach.systems import MultiVehicle9D

    (solution,) = solve_pairs(MultiVehicle9D(), 45, compile=False, progress=False).values()
    return solution
