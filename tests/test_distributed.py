"""Distributed training (training.distributed, ``reach train --distributed``): two gloo processes on the
CPU step as one process does on their combined batch, only rank 0 writes, and runs resume across
process counts; a start outside torchrun or with a batch that does not split is refused at once."""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from reach_cli import main
from training import TrainConfig, Trainer, load_network
from training.checkpoint import read_checkpoint
from training.distributed import TORCHRUN_VARIABLES, joined
from training.sampling import PointSampler, rank_seed

# a 9D system with policy labels (each process draws its share, refreshed every other step); a learning rate
# ten times the default's, so that three steps move the weights well past float noise; a constant schedule
# and no curriculum, so that a run of 3 steps resumed to 5 follows the schedule of a run of 5
TINY = {
    "system": "multivehicle9d",
    "lower_bound": "policy",
    "lower_bound_points": 32,
    "lower_bound_every": 2,
    "lower_bound_dt": 0.1,  # coarse labelling rollouts: the test needs labels, not good ones
    "width": 16,
    "points": 64,
    "lr": 1e-3,
    "schedule": "constant",
    "curriculum": 0.0,
    "log_every": 1,
    "checkpoint_every_s": 0.0,
}
TINY_ARGS = [
    *("--system", "multivehicle9d", "--lower-bound", "policy", "--lower-bound-points", "32"),
    *("--lower-bound-every", "2", "--lower-bound-dt", "0.1", "--width", "16", "--points", "64", "--lr", "1e-3"),
    *("--schedule", "constant", "--curriculum", "0", "--log-every", "1", "--checkpoint-every", "0"),
]


def _free_ports(count: int) -> list[int]:
    """``count`` distinct free TCP ports on this machine (one per process group the test starts)."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def _as_torchrun_starts(rank: int, port: int) -> None:
    """The environment torchrun gives process ``rank`` of two (one thread each, as torchrun sets too)."""
    os.environ.update(
        RANK=str(rank),
        WORLD_SIZE="2",
        LOCAL_RANK=str(rank),
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        OMP_NUM_THREADS="1",
    )
    torch.set_num_threads(1)


def _two_processes(rank: int, ports: list[int], tmp: Path) -> None:
    """Process ``rank`` of two: a new 3-step run through the library (rank 1 is given a directory of its
    own, which must stay unwritten), its gradients and weights saved for the test; then through
    ``reach train --distributed``, that run resumed to 5 steps, a 5-step run straight, and the
    one-process run ``single`` resumed to 4 steps."""
    _as_torchrun_starts(rank, ports[0])
    config = TrainConfig(steps=3, **TINY)
    with joined(config) as processes:
        trainer = Trainer(config, tmp / ("new" if rank == 0 else "new-rank1"), progress=False, processes=processes)
        trainer.train()
    grads = {name: p.grad for name, p in trainer.network.named_parameters()}
    torch.save({"grads": grads, "weights": trainer.network.state_dict()}, tmp / f"rank{rank}.pt")
    commands = (
        ["--resume", str(tmp / "new"), "--steps", "5"],
        ["--steps", "5", *TINY_ARGS, "--out", str(tmp / "straight")],
        ["--resume", str(tmp / "single"), "--steps", "4"],
    )
    for port, argv in zip(ports[1:], commands):
        _as_torchrun_starts(rank, port)
        assert main(["train", "--distributed", *argv]) == 0


class _CombinedBatch:
    """Both processes' points and labels of every step, concatenated (rank 0's first), each drawn from
    its process's stream: what one process trains on in the test's reference run."""

    def __init__(self, config: TrainConfig, trainer: Trainer) -> None:
        self.shares = [PointSampler(config, trainer.network, trainer.device, rank, 2) for rank in (0, 1)]
        self.generator = self.shares[0].generator  # what the trainer checkpoints
        self.refuted = None  # no refuted points (studies.train_until sets them on a real sampler)

    def points(self, tmax: float) -> tuple[torch.Tensor, torch.Tensor, None]:
        parts = [share.points(tmax) for share in self.shares]
        return torch.cat([x for x, _, _ in parts]), torch.cat([t for _, t, _ in parts]), None

    def lower_bound_labels(self, tmax: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        parts = [share.lower_bound_labels(tmax) for share in self.shares]
        return tuple(torch.cat(column) for column in zip(*parts))

    def refuted_batch(self, tmax: float) -> None:
        return None


def _spawn_two(ports: list[int], tmp: Path, limit_s: float = 180.0) -> None:
    """Run :func:`_two_processes` in two fresh processes; a hang fails the test after ``limit_s``
    instead of holding the suite (gloo waits 30 minutes for a missing peer)."""
    context = mp.spawn(_two_processes, args=(ports, tmp), nprocs=2, join=False)
    deadline = time.monotonic() + limit_s
    while not context.join(timeout=1.0):  # raises if a process failed (and ends the other)
        if time.monotonic() > deadline:
            for process in context.processes:
                process.kill()
            pytest.fail(f"the two training processes did not finish in {limit_s:.0f} s")


def _steps(run: Path) -> list[int]:
    return [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_two_processes_step_as_one_on_their_combined_batch_and_resume_in_any_count(tmp_path):
    Trainer(TrainConfig(steps=2, **TINY), tmp_path / "single", progress=False).train()
    _spawn_two(_free_ports(4), tmp_path)

    # the gradients of the third step and the weights after it: one process on the combined batch
    config = TrainConfig(steps=3, **TINY)
    reference = Trainer(config, tmp_path / "reference", progress=False)
    reference.sampler = _CombinedBatch(config, reference)
    reference.train()
    ranks = [torch.load(tmp_path / f"rank{rank}.pt") for rank in (0, 1)]
    for name, param in reference.network.named_parameters():
        torch.testing.assert_close(ranks[0]["grads"][name], param.grad, rtol=1e-4, atol=1e-5)
    for name, weight in reference.network.state_dict().items():
        torch.testing.assert_close(ranks[0]["weights"][name], weight, rtol=1e-5, atol=1e-6)
        assert torch.equal(ranks[1]["weights"][name], ranks[0]["weights"][name])  # the replicas stay identical
    assert not (tmp_path / "new-rank1").exists()  # rank 1 wrote nothing

    # resumed by as many processes: the run continues exactly, its checkpoint holds both streams
    resumed = load_network(tmp_path / "new" / "checkpoint.pt").state_dict()
    straight = load_network(tmp_path / "straight" / "checkpoint.pt").state_dict()
    assert all(torch.equal(resumed[k], straight[k]) for k in straight)
    assert _steps(tmp_path / "new") == [1, 2, 3, 4, 5]
    assert len(read_checkpoint(tmp_path / "new" / "checkpoint.pt")["streams"]) == 2

    # a one-process run resumed by two, and a two-process run resumed by one
    assert _steps(tmp_path / "single") == [1, 2, 3, 4]
    assert len(read_checkpoint(tmp_path / "single" / "checkpoint.pt")["streams"]) == 2
    with pytest.warns(UserWarning, match=r"written by 2 process\(es\), resumed by 1 at step 5"):
        alone = Trainer.resume(tmp_path / "straight", progress=False, steps=6)
    assert alone.train()["steps"] == 6 and _steps(tmp_path / "straight") == [1, 2, 3, 4, 5, 6]
    assert read_checkpoint(tmp_path / "straight" / "checkpoint.pt")["streams"] is None


@pytest.mark.parametrize(
    ("environment", "argv", "message"),
    [
        ({}, [], "torchrun, which sets RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT (not set here)"),
        ({"WORLD_SIZE": "two"}, [], "WORLD_SIZE='two' is not a non-negative integer"),
        ({"RANK": "2"}, [], "RANK 2 is not below WORLD_SIZE 2"),
        ({"MASTER_PORT": "70000"}, [], "MASTER_PORT 70000 is not a TCP port"),
        ({}, ["--points", "255"], "points 255 does not split evenly among 2 processes"),
    ],
)
def test_a_bad_distributed_start_is_one_line_before_any_work(tmp_path, monkeypatch, capsys, environment, argv, message):
    for name in TORCHRUN_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    if environment or argv:  # the first case has no torchrun environment, the others one with a fault
        given = {"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "29500"}
        for name, value in {**given, **environment}.items():
            monkeypatch.setenv(name, value)
    code = main(["train", "--distributed", "--steps", "1", *argv, "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert not (tmp_path / "run").exists()


def test_rank_seeds_keep_rank_0_on_the_run_seed_and_the_others_off_every_run_seed():
    assert rank_seed(7, 0) == 7
    assert all(rank_seed(seed, rank) >= 2**32 for seed in (0, 7, 2**32 - 1) for rank in range(1, 1000))


def test_waiting_for_peers_says_so_and_times_out_in_one_line(tmp_path):
    """A process whose peers never come says it waits, then gives up after --join-timeout with one
    line naming the rendezvous (torch's own timeout), not after torch's default half hour."""
    import socket
    import subprocess
    import sys
    import time

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    env = {**os.environ, "RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1"}
    env["MASTER_PORT"] = str(port)
    argv = [sys.executable, "-m", "reach", "train", "--distributed", "--join-timeout", "2", "--steps", "1"]
    start = time.monotonic()
    done = subprocess.run([*argv, "--out", str(tmp_path / "run")], env=env, capture_output=True, text=True, timeout=120)
    assert time.monotonic() - start < 60
    assert done.returncode == 2, done.stderr
    assert f"waiting for the 2 processes to join at 127.0.0.1:{port} (up to 2 s)" in done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert "error: distributed training: rank 0 waited 2 s" in last and "--join-timeout" in last, last
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
