"""Shared test settings: headless plotting, no progress bars, float64 helpers."""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("TQDM_DISABLE", "1")

import numpy as np
import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])

_threads_decided_for: list[object] = [None]


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Run each test module on the cores other processes leave free (reach.threads' policy, which the
    CLI and the library's long entry points apply for themselves), decided before its fixtures are
    built. torch's default of one thread per core spin-waits when another process keeps a core busy
    (measured: docs/results/benchmarks.md, *Threads when other processes share the cores*). What the
    tests compute does not depend on the count."""
    module = getattr(item, "module", None)
    if module is _threads_decided_for[0]:
        return
    _threads_decided_for[0] = module
    if os.environ.get("OMP_NUM_THREADS", "").strip():
        return  # the environment chose
    from reach.threads import free_cores

    torch.set_num_threads(free_cores())


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture(scope="session")
def air3d_grid():
    """An Air3D grid solution (51^3, 23 times over the 1.1 s horizon), solved once per session (~8 s)."""
    from groundtruth import SolverSettings
    from groundtruth.solver import solve
    from reach.systems import Air3D

    times = [round(1.1 * k / 22, 6) for k in range(23)]
    sol = solve(Air3D(), 51, times, settings=SolverSettings(compile=False), progress=False)
    sol.outside = "clamp"
    return sol


@pytest.fixture(scope="session")
def pair_grid():
    """The 9D system's cooperative two-car problem on a coarse 45^3 grid (11 times), ~3 s."""
    from groundtruth import SolverSettings
    from groundtruth.pairwise import solve_pairs
    from reach.systems import MultiVehicle9D

    (solution,) = solve_pairs(MultiVehicle9D(), 45, settings=SolverSettings(compile=False), progress=False).values()
    return solution


@pytest.fixture
def created_figures(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """A list that grows by one for every Matplotlib figure created while the test runs (renderers
    must not build one unless something is rendered)."""
    import matplotlib.figure

    created: list[int] = []
    original = matplotlib.figure.Figure.__init__

    def counting_init(self, *args, **kwargs):
        created.append(1)
        original(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "__init__", counting_init)
    return created


def step_in_lockstep(venv, singles, steps: int, action_range: float, check_info=None) -> int:
    """Step a vector env and its single-env twins with the same random actions (in
    ``[-action_range, action_range]``), asserting equal observations, rewards and end flags under
    NEXT_STEP autoreset; ``check_info(info)`` sees each vector step's info. Returns the resets."""
    n = len(singles)
    rng = np.random.default_rng(0)
    done = np.zeros(n, dtype=bool)
    resets = 0
    for _ in range(steps):
        actions = rng.uniform(-action_range, action_range, size=venv.action_space.shape).astype(np.float32)
        obs, rewards, terminated, truncated, info = venv.step(actions)
        if check_info is not None:
            check_info(info)
        for i, env in enumerate(singles):
            if done[i]:  # NEXT_STEP autoreset: this step resets sub-env i
                o, r, te, tr = env.reset()[0], 0.0, False, False
                resets += 1
            else:
                o, r, te, tr, _ = env.step(actions[i])
            np.testing.assert_allclose(obs[i], o, rtol=0, atol=1e-6)
            assert (rewards[i], terminated[i], truncated[i]) == (r, te, tr)
        done = terminated | truncated
    return resets


@pytest.fixture
def lockstep():
    """:func:`step_in_lockstep`, for tests comparing a vector env with single envs."""
    return step_in_lockstep


def nan_weight_copy(source: Path, target: Path) -> Path:
    """A copy of an exported ONNX filter with every weight matrix set to NaN (at least two), written
    to ``target`` with its digest sealed again (as an export of a NaN network would carry): a value
    function the runtimes must refuse to trust, in a file they accept as exported."""
    import onnx  # lazy: the export tests' dependency (the dev extra), not every test's
    from onnx import numpy_helper

    from reach_runtime.digest import seal  # lazy: loads ONNX Runtime, the export tests' dependency

    model = onnx.load(source)
    edited = 0
    for tensor in model.graph.initializer:
        array = numpy_helper.to_array(tensor)
        if array.ndim == 2 and array.dtype == np.float32:
            tensor.CopyFrom(numpy_helper.from_array(np.full_like(array, np.nan), tensor.name))
            edited += 1
    assert edited >= 2
    target.write_bytes(seal(model.SerializeToString(), str(target)))
    return target


@pytest.fixture
def nan_weights():
    """:func:`nan_weight_copy`, for the tests of the Python and C++ runtimes' refusal."""
    return nan_weight_copy
