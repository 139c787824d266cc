"""Layout sweeps: spec checks, snapshots, scoring, reports, resuming, the local and Ray backends."""

from __future__ import annotations

import json
import math

import pytest
import torch

from reach_cli import main as reach_main
from studies.sweeps import SweepSpec, claims, pareto_front, run_sweep
from studies.sweeps.report import _spearman, spearman_permutation_p, spread, summary_table
from studies.sweeps.spec import load_spec, store_spec
from training import TrainConfig, Trainer


def tiny_spec(**overrides) -> SweepSpec:
    """Seconds-long runs: width 16, 256 points a step, a fixed step count, a 21^3 ground truth."""
    base = dict(
        system="air3d",
        layouts=["ssssl", "rrrsl"],
        seeds=[0, 1],
        budget_s=None,
        steps=12,
        snapshots=3,
        width=16,
        train={"points": 256, "checkpoint_every_s": 0.0},
        grid=21,
        eval_time=1.0,
    )
    base.update(overrides)
    return SweepSpec(**base)


@pytest.fixture(scope="module")
def gt21(tmp_path_factory):
    """A coarse Air3D ground truth shared by the sweeps here (their own solve is tested once)."""
    from groundtruth import SolverSettings
    from groundtruth.solver import solve
    from reach.systems import Air3D

    path = tmp_path_factory.mktemp("gt") / "air3d21.npz"
    solve(Air3D(), 21, [0.1 * k for k in range(11)], settings=SolverSettings(compile=False), progress=False).save(path)
    return str(path)


# ---------------------------------------------------------------------- spec
@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"layouts": ["ssxsl"]}, "x"),
        ({"layouts": []}, "at least one layout"),
        ({"layouts": ["ssssl", "ssssl"]}, "repeat"),
        ({"seeds": []}, "seeds"),
        ({"steps": None}, "budget"),
        ({"snapshots": 0}, "snapshots"),
        ({"train": {"layout": "rrrrl"}}, "layout"),
        ({"train": {"pointz": 5}}, "pointz"),
        ({"evaluation": "grid"}, "evaluation"),
        ({"system": "multivehicle9d", "evaluation": "groundtruth"}, "9 dimensions"),
    ],
)
def test_bad_specs_are_named(overrides, message):
    with pytest.raises((ValueError, TypeError), match=message):
        tiny_spec(**overrides).validate()


def test_auto_evaluation_follows_the_dimension():
    assert tiny_spec().validate().evaluation == "groundtruth"
    assert tiny_spec(system="multivehicle9d").validate().evaluation == "rollout"


def test_stored_spec_may_grow_but_not_change(tmp_path):
    spec = tiny_spec().validate()
    store_spec(spec, tmp_path)
    store_spec(tiny_spec(layouts=["ssssl", "rrrsl", "srsrl"], seeds=[0]).validate(), tmp_path)  # grows: fine
    with pytest.raises(ValueError, match=r"width: 32 != 16"):
        store_spec(tiny_spec(width=32).validate(), tmp_path)
    assert load_spec(tmp_path).layouts == ["ssssl", "rrrsl", "srsrl"]
    (tmp_path / "sweep.json").write_text("{not json")
    with pytest.raises(ValueError, match="corrupt"):
        store_spec(spec, tmp_path)


# ---------------------------------------------------------------------- trainer snapshots
def test_trainer_takes_evenly_spaced_snapshots_and_the_last_is_the_final_network(tmp_path):
    from training.checkpoint import load_network

    cfg = TrainConfig(layout="srsl", width=8, points=64, steps=20, snapshots=4, checkpoint_every_s=0.0)
    Trainer(cfg, tmp_path / "run", progress=False).train()
    snaps = sorted((tmp_path / "run" / "snapshots").glob("*.pt"))
    assert [p.name for p in snaps] == ["001.pt", "002.pt", "003.pt", "004.pt"]
    steps = [json.loads(p.with_suffix(".json").read_text())["steps"] for p in snaps]
    assert steps == [5, 10, 15, 20]
    last = load_network(snaps[-1]).state_dict()
    final = load_network(tmp_path / "run" / "checkpoint.pt").state_dict()
    assert all(torch.equal(last[k], final[k]) for k in final)
    with pytest.raises(ValueError, match="snapshots"):
        TrainConfig(target_loss=0.1, snapshots=3).validate()


# ---------------------------------------------------------------------- report arithmetic
def test_pareto_front_keeps_only_undominated_points():
    pts = [(1.0, 0.5, "a"), (2.0, 0.4, "b"), (3.0, 0.7, "c"), (3.0, 0.6, "d"), (4.0, 0.9, "e")]
    assert [p[2] for p in pareto_front(pts, higher_is_better=True)] == ["a", "c", "e"]
    assert [p[2] for p in pareto_front(pts, higher_is_better=False)] == ["a", "b"]


def test_spearman_and_spread():
    assert _spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert _spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    assert math.isnan(_spearman([1, 1, 1], [1, 2, 3]))
    # ties in x: orderings that only swap tied points give the same rho, so p counts them all
    assert spearman_permutation_p([0, 1, 1], [1.0, 2.0, 3.0]) == pytest.approx(2 / 6)
    # beyond the exact limit: seeded random orderings, close to the exact value
    x, y = [0, 1, 2, 3, 4, 5, 6], [0.1, 0.3, 0.2, 0.5, 0.4, 0.7, 0.6]
    exact = spearman_permutation_p(x, y)
    assert spearman_permutation_p(x, y, max_exact=3, draws=50_000) == pytest.approx(exact, abs=0.005)
    s = spread([1.0, 3.0, float("nan")])
    assert (s["mean"], s["n"], s["min"], s["max"]) == (2.0, 2, 1.0, 3.0)
    assert s["std"] == pytest.approx(math.sqrt(2))


def _rows(scores: dict[str, list[float]]) -> list[dict]:
    return [
        {"layout": layout, "seed": k, "snapshot": 1, "wall": 1.0, "step": 10, "steps_per_s": 10.0, "iou": v}
        for layout, values in scores.items()
        for k, v in enumerate(values)
    ]


def test_claims_read_the_direction_of_the_data():
    supports = _rows({"ssssl": [0.9, 0.92], "ssrsl": [0.8, 0.82], "srrrl": [0.5, 0.52], "rrrrl": [0.3, 0.31]})
    (one, two) = claims(supports, "iou", higher_is_better=True)
    assert one["value"] == pytest.approx(1.0) and two["value"] > 0.3
    assert one["p_value"] == pytest.approx(1 / 24)  # the one best ordering of 4 layouts out of 4!
    assert two["p_value"] == pytest.approx(1 / 6)  # the best pair of 4 layouts out of C(4, 2)
    # the same data read as an error (lower is better) refutes both
    rho, gap = (c["value"] for c in claims(supports, "iou", higher_is_better=False))
    assert rho == pytest.approx(-1.0) and gap < -0.3
    table = summary_table(supports, [("iou", True)])
    assert table.index("`ssssl`") < table.index("`rrrrl`")  # best first


# ---------------------------------------------------------------------- sweeps end to end
def _mtimes(out):
    return {p.relative_to(out / "runs"): p.stat().st_mtime_ns for p in (out / "runs").rglob("*.pt")}


def test_sweep_writes_the_report_and_resumes_without_redoing_work(tmp_path, gt21):
    out = tmp_path / "sweep"
    spec = tiny_spec(groundtruth=gt21)
    report, failed = run_sweep(spec, out, progress=False, log=lambda *_: None)
    assert not failed
    data = json.loads((out / "results.json").read_text())
    rows = data["results"]
    assert len(rows) == 2 * 2 * 3
    assert {(r["layout"], r["seed"]) for r in rows} == {(a, s) for a in ("ssssl", "rrrsl") for s in (0, 1)}
    assert [r["step"] for r in rows if r["layout"] == "ssssl" and r["seed"] == 0] == [4, 8, 12]
    assert all(0 <= r["iou_volume"] <= 1 and r["mse_volume"] > 0 for r in rows)
    text = report.read_text()
    assert "`ssssl`" in text and "`rrrsl`" in text and "21x21x21" in text
    for name in ("pareto.png", "slices.png", "results.csv", "results.md"):
        assert (out / name).stat().st_size > 0
    # a second call reads everything back: no checkpoint rewritten, scores reused
    before = _mtimes(out)
    run_sweep(spec, out, progress=False, log=lambda *_: None)
    assert _mtimes(out) == before
    assert json.loads((out / "results.json").read_text())["results"] == rows


def test_interrupted_sweep_continues_where_it_stopped(tmp_path, gt21, monkeypatch):
    import studies.sweeps.backends as backends

    out = tmp_path / "sweep"
    spec = tiny_spec(groundtruth=gt21, seeds=[0])
    real = backends.run_task
    calls = []

    def interrupted(*args):
        calls.append(args[2])
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C during the second run
        return real(*args)

    monkeypatch.setattr(backends, "run_task", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(spec, out, progress=False, log=lambda *_: None)
    monkeypatch.setattr(backends, "run_task", real)
    first = _mtimes(out)
    assert first and all(str(p).startswith("ssssl-s0") for p in first)
    report, failed = run_sweep(spec, out, progress=False, log=lambda *_: None)
    assert not failed
    after = _mtimes(out)
    assert {p: after[p] for p in first} == first  # the finished run was not redone
    assert any(str(p).startswith("rrrsl-s0") for p in after)


def test_a_failing_run_is_reported_and_the_others_go_on(tmp_path, gt21, capsys):
    out = tmp_path / "sweep"
    run_dir = out / "runs" / "rrrsl-s0"
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(TrainConfig(layout="rrrsl", steps=3, width=4).to_json())  # foreign run
    code = reach_main(
        ["sweep", "--layouts", "ssssl,rrrsl", "--seeds", "1", "--steps", "6", "--snapshots", "2", "--width", "8",
         "--train", "points=128", "--groundtruth", gt21, "--eval-time", "1.0", "--out", str(out)]
    )  # fmt: skip
    assert code == 1
    assert "1 of 2 runs failed" in capsys.readouterr().err
    text = (out / "report.md").read_text()
    assert "Failed tasks" in text and "another configuration" in text and "`ssssl`" in text


def test_sweep_solves_and_caches_its_own_ground_truth(tmp_path):
    out = tmp_path / "sweep"
    spec = tiny_spec(layouts=["ssssl"], seeds=[0], steps=4, snapshots=1, grid=11)
    run_sweep(spec, out, progress=False, log=lambda *_: None)
    from groundtruth.solution import GridSolution

    gt = GridSolution.load(out / "groundtruth.npz")
    assert gt.grid.shape == (11, 11, 11) and float(gt.times[-1]) == pytest.approx(1.0)


def test_rollout_sweep_on_9d_scores_every_kth_snapshot(tmp_path, pair_grid):
    out = tmp_path / "sweep"
    pair_grid.save(tmp_path / "pair.npz")
    spec = SweepSpec(
        system="multivehicle9d",
        layouts=["ssrsl"],
        seeds=[0],
        budget_s=None,
        steps=6,
        snapshots=4,
        width=8,
        train={"points": 128},
        samples=64,
        scenario_samples=0,
        rollout_every=2,
        pairwise=str(tmp_path / "pair.npz"),
    )
    report, failed = run_sweep(spec, out, progress=False, log=lambda *_: None)
    assert not failed
    rows = json.loads((out / "results.json").read_text())["results"]
    assert [r["snapshot"] for r in rows] == [2, 4]
    for r in rows:
        assert 0 <= r["violation_rate"] <= 1 and r["delta"] >= 0 and 0 <= r["scenario_volume"] <= 1
        assert 0 <= r["containment_miss_rate"] <= r["union_fraction"] <= 1
    assert "violation %" in report.read_text() and "misses union %" in report.read_text()
    with pytest.raises(ValueError, match="rollout-evaluation"):
        tiny_spec(pairwise=str(tmp_path / "pair.npz")).validate()


def test_local_worker_processes_match_the_in_process_run(tmp_path, gt21):
    spec = tiny_spec(groundtruth=gt21, layouts=["ssrsl"], seeds=[0, 1], steps=6, snapshots=2)
    run_sweep(spec, tmp_path / "a", progress=False, log=lambda *_: None, threads=1)
    run_sweep(spec, tmp_path / "b", workers=2, progress=False, log=lambda *_: None)
    a = json.loads((tmp_path / "a" / "results.json").read_text())["results"]
    b = json.loads((tmp_path / "b" / "results.json").read_text())["results"]
    assert [(r["layout"], r["seed"], r["step"]) for r in a] == [(r["layout"], r["seed"], r["step"]) for r in b]
    assert [r["iou_volume"] for r in a] == pytest.approx([r["iou_volume"] for r in b], abs=1e-3)


def test_ray_backend_on_a_local_instance(tmp_path, gt21):
    ray = pytest.importorskip("ray")
    out = tmp_path / "sweep"
    spec = tiny_spec(groundtruth=gt21, layouts=["ssssl", "srsrl"], seeds=[0], steps=6, snapshots=2)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        report, failed = run_sweep(spec, out, backend="ray", progress=False, log=lambda *_: None)
    finally:
        ray.shutdown()
    assert not failed
    rows = json.loads((out / "results.json").read_text())["results"]
    assert {r["layout"] for r in rows} == {"ssssl", "srsrl"} and len(rows) == 4
    # the same directory continues with the local backend: nothing is retrained
    before = _mtimes(out)
    run_sweep(spec, out, progress=False, log=lambda *_: None)
    assert _mtimes(out) == before


def test_cli_seed_and_option_parsing_errors(tmp_path, capsys):
    assert reach_main(["sweep", "--seeds", "two", "--out", str(tmp_path)]) == 2
    assert "--seeds" in capsys.readouterr().err
    assert reach_main(["sweep", "--train", "points", "--out", str(tmp_path)]) == 2
    assert "KEY=VALUE" in capsys.readouterr().err
    assert reach_main(["sweep", "--budget", "1m", "--steps", "3", "--out", str(tmp_path)]) == 2
