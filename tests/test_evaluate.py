"""`reach evaluate` and `reach plot` end to end on tiny checkpoints: table, files, resume, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from reach.systems import Air3D, MultiVehicle9D
from reach_cli import main
from studies.batch_verification import load_results
from training import ValueNetwork, save_checkpoint


@pytest.fixture
def checkpoints(tmp_path: Path) -> Path:
    for i, layout in enumerate(["ssrsl", "rrrsl"]):
        torch.manual_seed(i)
        save_checkpoint(tmp_path / f"9d_{layout}.pt", ValueNetwork(MultiVehicle9D(), layout, width=16))
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "air3d.pt", ValueNetwork(Air3D(), "ssssl", width=16))
    (tmp_path / "broken.pt").write_bytes(b"not a checkpoint")
    net = ValueNetwork(MultiVehicle9D(), "ssssl", width=16)
    with torch.no_grad():
        net.layers[1].weight[0, 0] = float("nan")
    save_checkpoint(tmp_path / "nan.pt", net)
    return tmp_path


def test_evaluate_two_checkpoints_with_bad_ones_beside(checkpoints: Path, capsys):
    out = checkpoints / "res.csv"
    sources = [str(checkpoints / n) for n in ("9d_ssrsl.pt", "9d_rrrsl.pt", "broken.pt", "air3d.pt", "nan.pt")]
    args = ["evaluate", *sources, "--samples", "1500", "--scenario-samples", "500", "--out", str(out), "--plot"]
    assert main(args) == 3  # three sources fail: their rows say why, and so does the exit status
    captured = capsys.readouterr()
    table = captured.out
    assert "3 of 5 sources failed" in captured.err
    assert "| model | layout | violation % |" in table
    rows = {Path(r["source"]).name: r for r in load_results(out)}
    for name in ("9d_ssrsl.pt", "9d_rrrsl.pt"):
        r = rows[name]
        assert not r.get("error")
        assert r["samples"] == 1500 and r["scenario_states"] == 500
        assert r["violation_rate"] == pytest.approx(r["false_safe_rate"] + r["false_unsafe_rate"])
        assert r["collision_rate"] >= 0.10  # ~12.7 % of the box starts in collision
        assert 0 < r["eps"] < 1 and 0 <= r["scenario_volume"] <= 1
    assert "corrupt or unreadable" in rows["broken.pt"]["error"]
    assert "checkpoint is for system" in rows["air3d.pt"]["error"]
    assert "NaN or inf" in rows["nan.pt"]["error"]
    assert out.with_suffix(".md").read_text().count("\n") == 7
    assert (checkpoints / "res_violations.png").stat().st_size > 1000
    header = out.read_text().splitlines()[0]
    assert "violation_rate" in header and "delta" in header

    # resume: finished rows come back untouched, without recomputation
    before = json.loads(out.with_suffix(".json").read_text())
    assert main(args) == 3  # the bad sources fail again (and say so); the good rows are reused
    after = json.loads(out.with_suffix(".json").read_text())
    done = [r for r in before["results"] if not r.get("error")]
    again = [r for r in after["results"] if not r.get("error")]
    assert [r["wall_time"] for r in again] == [r["wall_time"] for r in done]

    # the same settings spelled out (a count given as the value it defaults to) merge, untouched
    assert main([*args, "--robust-samples", "500"]) == 3  # the bad sources still fail
    spelled = json.loads(out.with_suffix(".json").read_text())
    assert [r["wall_time"] for r in spelled["results"] if not r.get("error")] == [r["wall_time"] for r in done]
    # other settings into the same file are refused rather than mixed
    capsys.readouterr()
    assert main(["evaluate", *sources, "--samples", "1000", "--out", str(out)]) == 2
    assert "other settings" in capsys.readouterr().err
    assert main([*args, "--robust-samples", "400"]) == 2


def test_same_states_for_every_model(checkpoints: Path):
    out = checkpoints / "a.csv"
    src = str(checkpoints / "9d_ssrsl.pt")
    main(["evaluate", src, "--samples", "800", "--scenario-samples", "0", "--out", str(out)])
    main(["evaluate", src, "--samples", "800", "--scenario-samples", "0", "--out", str(checkpoints / "b.csv")])
    a, b = load_results(out)[0], load_results(checkpoints / "b.csv")[0]
    for key in ("violation_rate", "collision_rate", "delta"):
        assert a[key] == b[key]


def test_evaluate_errors_are_clear(tmp_path: Path, capsys):
    assert main(["evaluate", str(tmp_path / "nothing*"), "--out", str(tmp_path / "r.csv")]) == 2
    assert "matched no file" in capsys.readouterr().err
    (tmp_path / "dr.pth").write_bytes(b"x")
    assert main(["evaluate", str(tmp_path / "dr.pth"), "--out", str(tmp_path / "r.csv")]) == 2
    assert "stores neither system nor layout" in capsys.readouterr().err
    # a control period that is not a whole number of steps is refused in one line, before any rollout
    out = tmp_path / "held.csv"
    held = ["--control-period", "0.003", "--samples", "10", "--out", str(out)]
    assert main(["evaluate", "pretrained:air3d", *held]) == 2
    err = capsys.readouterr().err
    assert "control_period must be a whole multiple of dt" in err and "Traceback" not in err
    assert not out.exists()


def test_grid_solution_evaluates_as_control_experiment(air3d_grid, tmp_path: Path):
    path = tmp_path / "air3d.npz"
    air3d_grid.save(path)
    out = tmp_path / "grid.csv"
    assert main(["evaluate", str(path), "--samples", "2000", "--scenario-samples", "0", "--out", str(out)]) == 0
    row = load_results(out)[0]
    assert row["kind"] == "grid" and row["false_safe_rate"] < 3e-3


def test_plot_slices_and_episode(air3d_grid, checkpoints: Path, tmp_path: Path):
    grid = tmp_path / "air3d.npz"
    air3d_grid.save(grid)
    png = tmp_path / "slices.png"
    assert main(["plot", "slices", str(checkpoints / "air3d.pt"), "--ground-truth", str(grid), "--out", str(png)]) == 0
    assert png.stat().st_size > 5000
    png9 = tmp_path / "slices9.png"
    assert main(["plot", "slices", str(checkpoints / "9d_ssrsl.pt"), "--out", str(png9)]) == 0
    gif = tmp_path / "episode.gif"
    assert main(["plot", "episode", str(grid), "--out", str(gif), "--seed", "1"]) == 0
    import imageio.v3 as iio

    frames = iio.imread(gif, index=None)
    assert frames.shape[0] > 10


def test_evaluate_reports_containment_against_pairwise_union(pair_grid, checkpoints: Path):
    pair = checkpoints / "pair.npz"
    pair_grid.save(pair)
    out = checkpoints / "c.csv"
    src = [str(checkpoints / "9d_ssrsl.pt"), str(pair)]
    assert (
        main(
            [
                "evaluate",
                *src,
                "--system",
                "multivehicle9d",
                "--samples",
                "1000",
                "--scenario-samples",
                "0",
                "--pairwise",
                str(pair),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = {r["kind"]: r for r in load_results(out)}
    assert rows["pairwise"]["containment_miss_rate"] == 0.0  # the union contains itself
    assert 0.15 < rows["pairwise"]["union_fraction"] < 0.6
    learned = rows["reach"]
    assert 0.0 <= learned["containment_ci_low"] <= learned["containment_miss_rate"] <= learned["containment_ci_high"]
    assert "misses union %" in out.with_suffix(".md").read_text()


def test_bfloat16_evaluation_applies_to_networks_and_records_it(air3d_grid, checkpoints: Path, tmp_path: Path):
    grid = tmp_path / "air3d.npz"
    air3d_grid.save(grid)
    common = ["--system", "air3d", "--samples", "300", "--scenario-samples", "0", "--dt", "0.01"]
    exact_out, fast_out = tmp_path / "exact.csv", tmp_path / "fast.csv"
    sources = [str(grid), str(checkpoints / "air3d.pt")]
    assert main(["evaluate", *sources, *common, "--out", str(exact_out)]) == 0
    assert main(["evaluate", *sources, *common, "--matmul-precision", "bfloat16", "--out", str(fast_out)]) == 0
    exact, fast = load_results(exact_out), load_results(fast_out)
    assert [r["matmul_precision"] for r in exact] == ["float32", "float32"]
    assert [r["matmul_precision"] for r in fast] == ["float32", "bfloat16"]  # the grid stays exact
    assert fast[0]["collision_rate"] == exact[0]["collision_rate"]
    assert abs(fast[1]["collision_rate"] - exact[1]["collision_rate"]) <= 0.03


@settings(max_examples=60, deadline=None)
@given(
    stored=st.lists(st.integers(0, 9), unique=True, max_size=8),
    new=st.lists(st.integers(0, 9), unique=True, max_size=8),
)
def test_merge_rows_keeps_stored_order_lets_reruns_supersede_and_appends_the_rest(stored, new):
    """The merge both result tables use: every stored key stays in place (its new row if rerun), new
    keys follow in their order, no key twice and no row lost."""
    from studies.tables import merge_rows

    merged = merge_rows([{"k": k, "run": "old"} for k in stored], [{"k": k, "run": "new"} for k in new], key="k")
    assert [r["k"] for r in merged] == stored + [k for k in new if k not in stored]
    assert all(r["run"] == ("new" if r["k"] in new else "old") for r in merged)


@pytest.mark.slow  # run by name in .ci/run: keeps the default suite under 10 minutes
def test_capped_networks_evaluate_on_the_chosen_device(pair_grid, checkpoints: Path, device: str):
    """`min:` and `cap:` of a network and the union of pairwise BRTs under `reach evaluate --device`.
    The first GPU run of these failed: the misses of the union were computed from states on the CPU,
    the network returned its values on the GPU and the union on the CPU, and the minimum refused to
    mix them. A value function now answers on the states' device, wherever its weights are; with
    states on either device the composition's value and gradient come back there."""
    from groundtruth.pairwise import PairwiseUnion
    from reach.value_function import MinimumOf
    from training import NeuralValueFunction

    system = MultiVehicle9D()
    torch.manual_seed(0)
    net = ValueNetwork(system, "ssssl", width=16).to(device)
    x = system.sample_states(64, generator=torch.Generator().manual_seed(1))
    for steer_by in (None, 0):
        vf = MinimumOf(NeuralValueFunction(net), PairwiseUnion(system, pair_grid), steer_by=steer_by)
        on_cpu = vf.value(x, 1.0)
        for where in ("cpu", device):
            v, g = vf.value_and_gradient(x.to(where), 1.0)
            assert v.device.type == g.device.type == torch.device(where).type
            assert vf.value(x.to(where), 1.0).device.type == torch.device(where).type
            assert on_cpu.device.type == "cpu" and torch.allclose(v.cpu(), on_cpu, atol=1e-5)

    pair = checkpoints / "pair.npz"
    pair_grid.save(pair)
    out = checkpoints / "capped.csv"
    run = checkpoints / "9d_ssrsl.pt"
    sources = [f"min:{run},{pair}", f"cap:{run},{pair}"]
    counts = ["--samples", "300", "--scenario-samples", "200", "--robust-samples", "200"]
    args = ["evaluate", *sources, "--system", "multivehicle9d", *counts, "--pairwise", str(pair)]
    assert main([*args, "--device", device, "--out", str(out)]) == 0
    rows = load_results(out)
    assert len(rows) == 2 and not any(r.get("error") for r in rows), [r.get("error") for r in rows]
    assert all(r["containment_miss_rate"] == 0.0 for r in rows)  # a minimum with the union misses none of it


def test_chunk_size_follows_the_device_unless_given(checkpoints: Path, monkeypatch):
    """A CUDA GPU rolls out 262,144 states at once by default (the CPU's 16,384 leaves it launch-bound);
    ``reach evaluate`` records the size it used, and a given ``--chunk-size`` wins."""
    from safety.verification.rollout import CUDA_CHUNK_SIZE, RolloutSettings, default_chunk_size

    assert default_chunk_size("cuda") == CUDA_CHUNK_SIZE == 262_144
    assert default_chunk_size("cpu") == default_chunk_size(torch.device("cpu")) == RolloutSettings.chunk_size
    used = []
    monkeypatch.setattr(
        "studies.batch_verification.evaluate_many", lambda sources, out, settings, **kw: used.append(settings) or []
    )
    source = str(checkpoints / "air3d.pt")
    for extra in ([], ["--chunk-size", "999"]):
        main(["evaluate", source, "--samples", "10", "--out", str(checkpoints / "r.csv"), *extra])
    assert [s.chunk_size for s in used] == [16384, 999]


def test_share_samples_is_a_setting_of_the_table(air3d_grid, tmp_path: Path):
    """``--share-samples`` is recorded with the table's settings, its rows say how many of the
    delta-level's states were reused, and a table of unshared rows refuses shared ones."""
    grid = tmp_path / "air3d.npz"
    air3d_grid.save(grid)
    counts = ["--samples", "300", "--scenario-samples", "200", "--robust-samples", "2000", "--target-eps", "0.05"]
    args = ["evaluate", str(grid), *counts, "--dt", "0.01"]
    assert main([*args, "--out", str(tmp_path / "alone.csv")]) == 0
    assert main([*args, "--out", str(tmp_path / "alone.csv"), "--share-samples"]) == 2  # other settings: refused
    out = tmp_path / "shared.csv"
    assert main([*args, "--out", str(out), "--share-samples"]) == 0
    (alone,), (shared,) = load_results(tmp_path / "alone.csv"), load_results(out)
    assert json.loads(out.with_suffix(".json").read_text())["settings"]["share_samples"] is True
    assert 0 < shared["scenario_reused"] <= 200 and "scenario_reused" not in alone
    assert shared["robust_scenario_volume"] == alone["robust_scenario_volume"]
