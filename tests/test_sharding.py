"""Verification sharded over Ray: the blocks of every rollout as Ray tasks on a local instance give
the same row, bit for bit, as one process; through the rollout store and from the CLI."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("ray")

from reach.systems import Air3D
from reach_cli import main
from safety.verification.sharding import RayBlocks, make_backend
from safety.verification.verify import VerifySettings, sample_states, verify
from studies.batch_verification import evaluate_many
from training.network import NeuralValueFunction, ValueNetwork

#: columns that time the work rather than describe the outcome
TIMING = {"wall_time", "rollout_time", "time_s", "rollout_blocks_resumed"}


@pytest.fixture(scope="module")
def ray_blocks():
    with RayBlocks(cpus_per_task=1) as blocks:
        yield blocks


def _outcomes(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in TIMING and "time" not in k and "second" not in k}


def test_sharded_rows_equal_the_single_process_bit_for_bit(ray_blocks, tmp_path):
    torch.manual_seed(0)
    vf = NeuralValueFunction(ValueNetwork(Air3D(), "ssl", width=16))
    # two blocks of each rollout, the second one short (a block's cost is its steps, not its states)
    settings = VerifySettings(samples=60, scenario_samples=60, robust_samples=0, seed=3, chunk_size=50)
    states = sample_states(vf.system, settings.samples, settings.seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the workers' thread count (one core per task)
    try:
        alone = verify(vf, states, settings, progress=False)
        sharded = verify(vf, states, settings, progress=False, backend=ray_blocks)
    finally:
        torch.set_num_threads(threads)
    assert _outcomes(sharded) == _outcomes(alone)
    # through the rollout store (reach evaluate's path): the same row, and the blocks saved as they came
    path = tmp_path / "vf.pt"
    from training.checkpoint import save_checkpoint

    save_checkpoint(path, vf.network)
    (local,) = evaluate_many([str(path)], tmp_path / "local.csv", settings, progress=False)
    (ray_row,) = evaluate_many([str(path)], tmp_path / "ray.csv", settings, progress=False, backend=ray_blocks)
    assert _outcomes({**ray_row, "source": None}) == _outcomes({**local, "source": None})


def test_backend_choices_are_checked_before_any_work(tmp_path, capsys):
    assert make_backend("local") is None and isinstance(make_backend("ray"), RayBlocks)
    with pytest.raises(ValueError, match="--address needs --backend ray"):
        make_backend("local", "ray://head:10001")
    with pytest.raises(ValueError, match=r"backend must be one of \('local', 'ray'\), got 'dask'"):
        make_backend("dask")
    args = ["evaluate", "pretrained:air3d", "--samples", "10", "--address", "x:1", "--out", str(tmp_path / "r.csv")]
    assert main(args) == 2
    assert "--address needs --backend ray" in capsys.readouterr().err
    assert not (tmp_path / "r.csv").exists()


def test_ray_setup_is_refused_up_front_in_one_line(tmp_path, monkeypatch, capsys):
    """A missing Ray, a malformed address and an address nothing answers at are bad input (exit 2),
    refused within seconds and before any source is evaluated (not a failed source, exit 3)."""
    import importlib.util
    import socket
    import time

    from reach_cli import main
    from safety.verification import sharding

    real_find_spec = importlib.util.find_spec

    def ray_as(found):
        return lambda name, *a: found if name == "ray" else real_find_spec(name, *a)

    monkeypatch.setattr(importlib.util, "find_spec", ray_as(None))
    with pytest.raises(ValueError, match=r"needs Ray: pip install"):
        sharding.check_ray_ready(None)
    out = tmp_path / "r.csv"
    assert main(["evaluate", "pretrained:air3d", "--samples", "10", "--backend", "ray", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "needs Ray" in err and len(err.strip().splitlines()) == 1 and not out.exists()
    monkeypatch.setattr(importlib.util, "find_spec", ray_as(object()))
    for bad in ("nohost", "host:port", ":6379", "host:70000"):
        with pytest.raises(ValueError, match="is not HOST:PORT"):
            sharding.check_ray_ready(bad)
    with socket.socket() as sock:  # a port nothing listens on: bound, never listening
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
        start = time.monotonic()
        with pytest.raises(ValueError, match=rf"127.0.0.1:{port}: no Ray cluster answers there"):
            sharding.check_ray_ready(f"127.0.0.1:{port}", timeout=2.0)
        assert time.monotonic() - start < 10
        argv = ["evaluate", "pretrained:air3d", "--samples", "10", "--backend", "ray", "--address", f"127.0.0.1:{port}"]
        assert main([*argv, "--out", str(out)]) == 2
        assert "no Ray cluster answers" in capsys.readouterr().err and not out.exists()
    with socket.socket() as server:  # something listening: the address passes the check
        server.bind(("127.0.0.1", 0))
        server.listen()
        sharding.check_ray_ready(f"ray://127.0.0.1:{server.getsockname()[1]}")
    sharding.check_ray_ready("auto")
