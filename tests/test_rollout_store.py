"""Interrupted verifications resume: rollout blocks kept on disk, trusted only when they match."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import safety.verification.rollout_store as rollout_store
from reach.systems import Air3D
from reach.threads import thread_policy
from safety.verification.rollout_store import RolloutStore
from safety.verification.verify import VerifySettings, sample_states
from studies.batch_verification import evaluate_many
from training import NeuralValueFunction, ValueNetwork

#: columns that time the run rather than describe the value function
TIMING = {"wall_time", "rollout_seconds", "state_steps_per_second", "rollout_blocks_resumed"}


class SimulatedKillError(Exception):
    """Stands for SIGKILL or Ctrl-C in the middle of a verification."""


def _counting_rollout(monkeypatch: pytest.MonkeyPatch, fail_at: int | None = None) -> list[int]:
    """Count the store's simulated blocks; raise on block ``fail_at`` (1-based) if given."""
    calls: list[int] = []
    real = rollout_store.rollout

    def counted(*args, **kwargs):
        calls.append(1)
        if fail_at is not None and len(calls) == fail_at:
            raise SimulatedKillError
        return real(*args, **kwargs)

    monkeypatch.setattr(rollout_store, "rollout", counted)
    return calls


@pytest.mark.slow  # run by name in .ci/run: keeps the default suite under 10 minutes
def test_an_interrupted_evaluation_resumes_to_the_same_row(tmp_path: Path, monkeypatch) -> None:
    """A verification killed after three of its eight rollout blocks (two each of the samples, the
    delta-level's fresh states and the robust search and check: the samples' done, the fresh
    states' begun) loads those three when rerun, simulates only the rest, and writes the row an
    uninterrupted run writes; the store is gone once the row is written. (A block's cost is its
    steps, not its states: the block count sets this test's time.)"""
    run = "pretrained:air3d"
    settings = VerifySettings(samples=200, scenario_samples=200, robust_samples=200, target_eps=0.2, chunk_size=128)
    whole = evaluate_many([run], tmp_path / "whole.csv", settings, progress=False)[0]
    assert not whole.get("error") and whole["rollout_blocks_resumed"] == 0, whole.get("error")
    assert whole["robust_failures"] is not None and whole["scenario_states"] == 200, whole.get("robust_error")
    assert not (tmp_path / "whole.csv.rollouts").exists()
    blocks = 2 + 2 + 2 + 2  # ceil(200 / 128) for the samples, the fresh states, the search and the check

    out = tmp_path / "resumed.csv"
    with monkeypatch.context() as m:
        _counting_rollout(m, fail_at=4)
        with pytest.raises(SimulatedKillError):
            evaluate_many([run], out, settings, progress=False)
    kept = list((tmp_path / "resumed.csv.rollouts").rglob("*.pt"))
    assert len(kept) == 3
    with monkeypatch.context() as m:
        calls = _counting_rollout(m)
        resumed = evaluate_many([run], out, settings, progress=False)[0]
    assert len(calls) == blocks - 3 and resumed["rollout_blocks_resumed"] == 3
    assert {k: v for k, v in resumed.items() if k not in TIMING} == {k: v for k, v in whole.items() if k not in TIMING}
    assert not (tmp_path / "resumed.csv.rollouts").exists()


def test_the_store_distrusts_blocks_it_cannot_vouch_for(tmp_path: Path) -> None:
    """Blocks are reused only for the same key and the same states: a damaged file, a block of
    other states or of the wrong shape is simulated again, and a store opened under another key
    (another value function or settings) starts empty."""
    with thread_policy():  # torch's default threads collapse beside other work
        _distrust(tmp_path)


def _distrust(tmp_path: Path) -> None:
    torch.manual_seed(0)
    vf = NeuralValueFunction(ValueNetwork(Air3D(), "ssssl", width=16))
    x = sample_states(vf.system, 200, 0)
    kw = {"chunk_size": 50, "progress": False}
    first = RolloutStore(tmp_path / "s", {"vf": 1}).rollout("samples", vf, x, **kw)
    files = sorted((tmp_path / "s").glob("samples-*.pt"))
    assert len(files) == 4

    files[0].write_bytes(b"not a block")
    payload = torch.load(files[1], weights_only=True)
    payload["collided"] = payload["collided"][:10]
    torch.save(payload, files[1])
    store = RolloutStore(tmp_path / "s", {"vf": 1})
    again = store.rollout("samples", vf, x, **kw)
    assert (store.simulated_blocks, store.loaded_blocks) == (2, 2)
    for name in ("initial_value", "collided", "collision_time", "decided_time"):
        torch.testing.assert_close(getattr(again, name), getattr(first, name), rtol=0, atol=0, equal_nan=True)

    other = x.clone()
    other[0, 0] += 0.01
    store = RolloutStore(tmp_path / "s", {"vf": 1})
    store.rollout("samples", vf, other, **kw)
    assert (store.simulated_blocks, store.loaded_blocks) == (1, 3)

    store = RolloutStore(tmp_path / "s", {"vf": 2})
    assert not list((tmp_path / "s").glob("*.pt"))
    store.rollout("samples", vf, x, **kw)
    assert (store.simulated_blocks, store.loaded_blocks) == (4, 0)
    with pytest.raises(ValueError, match="record=True"):
        store.rollout("samples", vf, x, record=True, **kw)


def test_a_changed_outcome_or_a_foreign_key_is_simulated_again(tmp_path: Path) -> None:
    """The block digest covers every outcome: one flipped bit, or a block written for another key
    into this store's directory, is not trusted."""
    with thread_policy():
        torch.manual_seed(0)
        vf = NeuralValueFunction(ValueNetwork(Air3D(), "ssssl", width=16))
        x = sample_states(vf.system, 100, 0)
        kw = {"chunk_size": 50, "progress": False}
        with RolloutStore(tmp_path / "s", {"vf": 1}) as store:
            first = store.rollout("samples", vf, x, **kw)
        files = sorted((tmp_path / "s").glob("samples-*.pt"))
        payload = torch.load(files[0], weights_only=True)
        payload["collided"] = payload["collided"].clone()
        payload["collided"][3] = ~payload["collided"][3]  # one flipped outcome
        torch.save(payload, files[0])
        foreign = torch.load(files[1], weights_only=True)
        foreign["key"] = rollout_store.key_digest({"vf": 2})  # a block another key's process wrote
        foreign["block_digest"] = rollout_store.block_digest(foreign["key"], foreign["digest"], foreign)
        torch.save(foreign, files[1])
        with RolloutStore(tmp_path / "s", {"vf": 1}) as store:
            again = store.rollout("samples", vf, x, **kw)
            assert (store.simulated_blocks, store.loaded_blocks) == (2, 0)
        torch.testing.assert_close(again.collided, first.collided, rtol=0, atol=0)


def test_a_second_process_is_refused_before_it_simulates(tmp_path: Path) -> None:
    import subprocess
    import sys

    from reach.locking import LockedError

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from safety.verification.rollout_store import RolloutStore\n"
            f"s = RolloutStore({str(tmp_path / 's')!r}, {{'vf': 1}})\n"
            "print('held', flush=True)\n"
            "time.sleep(60)\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(LockedError, match=r"rollout store .* is in use by process"):
            RolloutStore(tmp_path / "s", {"vf": 2})
        assert (tmp_path / "s" / "manifest.json").read_text() == '{"vf": 1}'  # not emptied by the refused one
    finally:
        holder.kill()
        holder.wait()
    RolloutStore(tmp_path / "s", {"vf": 2}).close()  # free once the holder is gone


def test_a_table_claimed_with_other_settings_refuses_the_second_run_before_work(tmp_path: Path) -> None:
    torch.manual_seed(0)
    run = tmp_path / "a.pt"
    from training.checkpoint import save_checkpoint

    save_checkpoint(run, ValueNetwork(Air3D(), "ssssl", width=16))
    out = tmp_path / "t.csv"
    evaluate_many([str(run)], out, VerifySettings(samples=200, scenario_samples=0, robust_samples=0), progress=False)
    with pytest.raises(ValueError, match="holds results for other settings"):
        evaluate_many(
            [str(run)], out, VerifySettings(samples=200, scenario_samples=0, robust_samples=0, dt=0.005), progress=False
        )


def test_a_step_longer_than_the_horizon_and_an_oversized_verification_are_refused() -> None:
    from safety.verification.verify import check_for_system

    system = Air3D()
    with pytest.raises(ValueError, match="dt must not exceed the horizon"):
        check_for_system(system, VerifySettings(dt=1.2))
    with pytest.raises(ValueError, match="dt must not exceed the horizon"):
        VerifySettings(dt=1.2, horizon=1.0)
    with pytest.raises(ValueError, match=r"needs about .* GiB, but .* GiB is available; use fewer --samples"):
        check_for_system(system, VerifySettings(samples=10**12))
