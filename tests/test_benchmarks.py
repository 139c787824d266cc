"""The benchmark entry point runs its scripts (smoke size) and compares with an earlier run."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow  # run by name in .ci/run: keeps the default suite under 10 minutes
def test_run_all_quick_and_compare(tmp_path: Path):
    from reach.threads import free_cores

    cmd = [sys.executable, str(ROOT / "benchmarks" / "run_all.py"), "--quick", "--only", "rollouts"]
    # the benchmark takes torch's default of a thread per core, which spin-wait on each other where
    # other work keeps a core busy (reach.threads): beside a training run this test took 163 s, and
    # 22 s on the cores left free, as the reach command itself would choose
    env = {**os.environ, "OMP_NUM_THREADS": str(free_cores())}
    first = subprocess.run([*cmd, "--out", str(tmp_path / "a")], capture_output=True, text=True, cwd=ROOT, env=env)
    assert first.returncode == 0, first.stderr
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["runs"][0]["exit"] == 0 and "agrees with reach" in summary["runs"][0]["tables"]
    assert summary["runs"][0]["command"] == "python benchmarks/bench_rollouts.py --quick"
    second = subprocess.run(
        [*cmd, "--out", str(tmp_path / "b"), "--compare", str(tmp_path / "a" / "summary.json")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
    )
    assert second.returncode == 0, second.stderr
    assert "| previous wall (s) | ratio |" in second.stdout
    assert "## rollouts:" in (tmp_path / "b" / "report.md").read_text()


def _results(path: Path, labels: list[str]) -> None:
    keys = ["violation_rate", "false_safe_rate", "collision_rate", "containment_miss_rate", "scenario_volume"]
    lines = [",".join(["label", *keys])]
    lines += [",".join([label, *(f"{0.01 * (i + 1) + 0.001 * k:.4f}" for k in range(len(keys)))]) for i, label in
              enumerate(labels)]  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def _recording_trainer(calls: list) -> type:
    """A stand-in for :class:`training.Trainer` in the 9D study: records ``("train", run, config)``
    for a new run and ``("resume", run, overrides)`` for a resumed one, and trains nothing."""

    class Recording:
        def __init__(self, config, run_dir):
            calls.append(("train", Path(run_dir), config))

        @classmethod
        def resume(cls, run_dir, **overrides):
            calls.append(("resume", Path(run_dir), overrides))
            return cls.__new__(cls)

        def train(self):
            return {"run_dir": "run", "steps": 0, "wall_time_s": 0.0, "stopped": "steps"}

    return Recording


def test_nine_d_study_and_ablation_reports_read_the_scored_runs(tmp_path: Path):
    """The 9D accuracy-against-time report plots each metric against the budget; the ablation report
    averages each change over its seeds, taking the baseline from the study's runs."""
    study, ablation = tmp_path / "study", tmp_path / "ablation"
    _results(study / "results.csv", ["ssssl-10m-seed0", "ssssl-10m-seed1", "ssssl-30m-seed0"])
    run = [sys.executable, str(ROOT / "benchmarks" / "nine_d_accuracy_vs_time.py"), "report", "--out", str(study)]
    out = subprocess.run(run, capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert "| ssssl-30m-seed0 | 0.0300 |" in out.stdout
    assert (study / "accuracy_vs_time.png").stat().st_size > 10_000
    for seed in (0, 1):
        (study / "runs" / f"ssssl-10m-seed{seed}").mkdir(parents=True)
        (study / "runs" / f"ssssl-10m-seed{seed}" / "checkpoint.pt").write_bytes(b"")
    _results(ablation / "results.csv", ["ssssl-10m-seed0", "ssssl-10m-seed1", "upper-bound-10m-seed0"])
    run = [sys.executable, str(ROOT / "benchmarks" / "nine_d_ablation.py"), "report", "--out", str(ablation)]
    out = subprocess.run([*run, "--study", str(study)], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert "| baseline | 2 | 0.015 (0.01, 0.02) |" in out.stdout
    assert "| upper-bound | 1 | 0.03 (0.03) |" in out.stdout
    layouts = tmp_path / "layouts"
    _results(layouts / "results.csv", ["ssrsl-15m-seed0", "ssrsl-15m-seed1", "rrrrl-15m-seed0"])
    run = [sys.executable, str(ROOT / "benchmarks" / "nine_d_layouts.py"), "report", "--out", str(layouts)]
    out = subprocess.run(run, capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    # equal wall time: the cheaper ReLU layout trains more steps; the paper's rate stands beside ours
    assert "| ssrsl | 14685 | 2 | 0.015 (0.01, 0.02) |" in out.stdout and out.stdout.rstrip().endswith("23.53 |")
    assert "| rrrrl | 18125 | 1 | 0.03 (0.03) |" in out.stdout


def test_nine_d_study_cells_show_unbounded_seeds_and_runs_move_between_devices(tmp_path: Path, monkeypatch):
    """A seed whose robust search bounded nothing (NaN) shows as "none" and withholds the mean; a
    study run trains and resumes on the device the script was given."""
    from studies import step_budget_report as report
    from studies import step_budget_study as study

    rows = [
        {"label": "x-seed1", "robust_scenario_volume": "0.7", "violation_rate": "0.02"},
        {"label": "x-seed0", "robust_scenario_volume": "nan", "violation_rate": "0.04"},
    ]
    count, cells = report.seed_cells(rows, {"x-seed0", "x-seed1"}, ["robust_scenario_volume", "violation_rate"])
    assert count == 2 and cells == ["- (none, 0.7)", "0.03 (0.04, 0.02)"]

    calls: list[tuple] = []
    monkeypatch.setattr(study, "Trainer", _recording_trainer(calls))
    run = tmp_path / "run"
    assert study.train_or_resume(run, 50, 3, {"layout": "rrrrl"}, device="cuda") == 0
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(b"")
    assert study.train_or_resume(run, 80, 3, {"layout": "rrrrl"}, device="cpu") == 0
    (kind, path, new), resumed = calls
    assert kind == "train" and path == run and new.system == "multivehicle9d" and new.seed == 3
    assert new.device == "cuda" and new.steps == 50 and new.layout == "rrrrl"
    assert resumed == ("resume", run, {"steps": 80, "device": "cpu"})

    # only a run that reached its steps is scored: a stopped one has a checkpoint too
    assert not study.finished(tmp_path / "missing")
    (run / "checkpoint.json").write_text(json.dumps({"steps": 79, "config": {"steps": 80}}))
    assert not study.finished(run)
    (run / "checkpoint.json").write_text(json.dumps({"steps": 80, "config": {"steps": 80}}))
    assert study.finished(run)


def test_step_budget_study_trains_resumes_and_scores_through_the_library(tmp_path: Path, pair_grid):
    """The study's stages on the library itself (small): a run trained against the pairwise union
    is finished, resumes to a longer budget, and is scored into the table the report reads; a run
    that never trained is left out."""
    from studies import step_budget_report as report
    from studies import step_budget_study as study

    pairwise = pair_grid.save(tmp_path / "pair.npz")
    small = {"layout": "ssl", "width": 8, "points": 64, "upper_bound": str(pairwise)}
    out = tmp_path / "s"
    run = study.run_path(out, "tiny", 0.01, 0)
    assert study.train_runs([study.PlannedRun(run, 3, 0, small)]) == 0 and study.finished(run)
    assert study.train_or_resume(run, 5, 0, small) == 0
    assert json.loads((run / "checkpoint.json").read_text())["steps"] == 5 and study.finished(run)
    scoring = study.Scoring(samples=64, scenario_samples=0, pairwise=str(pairwise))
    assert study.score_runs([run, study.run_path(out, "tiny", 0.01, 1)], out, scoring) == 0
    rows = report.read_results(out)
    assert [r["label"] for r in rows] == [run.name] and rows[0]["containment_miss_rate"] != ""
    assert report.scored_settings(out)["samples"] == 64


def test_nine_d_study_scripts_refuse_a_bad_device_or_chunk_size_before_any_work(tmp_path: Path, monkeypatch, capsys):
    """--device and --chunk-size are checked by the library's own argument types: one clear error,
    exit 2, and nothing trained or written. (Each script's ``main``, in this process: six fresh
    interpreters importing torch cost ~10 s; an exception other than the parser's exit fails here.)"""
    import importlib

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    for script in ("nine_d_accuracy_vs_time", "nine_d_ablation", "nine_d_layouts"):
        main = importlib.import_module(script).main
        for bad, words in ((["--device", "tpu"], "--device"), (["--chunk-size", "0"], "--chunk-size")):
            try:
                code = main(["train", "--out", str(tmp_path / "s"), *bad])
            except SystemExit as exit_info:  # argparse's error exit
                code = exit_info.code
            err = capsys.readouterr().err
            assert code == 2 and words in err and "Traceback" not in err, err
    assert not (tmp_path / "s").exists()


def test_ablation_report_takes_its_baseline_scores_from_the_study_when_scored_alike(tmp_path: Path):
    """The ablation's baseline is the time study's run; where the study scored it with the same
    settings, the ablation's report shows it without scoring it twice, and not otherwise."""
    study, ablation = tmp_path / "study", tmp_path / "ablation"
    _results(study / "results.csv", ["ssssl-10m-seed0", "ssssl-10m-seed1"])
    _results(ablation / "results.csv", ["zero-level-10m-seed0", "zero-level-10m-seed1"])
    for seed in (0, 1):
        (study / "runs" / f"ssssl-10m-seed{seed}").mkdir(parents=True)
        (study / "runs" / f"ssssl-10m-seed{seed}" / "checkpoint.pt").write_bytes(b"")
    run = [sys.executable, str(ROOT / "benchmarks" / "nine_d_ablation.py"), "report", "--out", str(ablation)]
    run += ["--study", str(study), "--rows", "baseline,zero-level"]
    for table, samples in ((study, 100_000), (ablation, 100_000)):
        (table / "results.json").write_text(json.dumps({"settings": {"samples": samples}}))
    out = subprocess.run(run, capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert "| baseline | 2 | 0.015 (0.01, 0.02) |" in out.stdout and "| zero-level | 2 |" in out.stdout
    (study / "results.json").write_text(json.dumps({"settings": {"samples": 20_000}}))
    out = subprocess.run(run, capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0 and "| baseline |" not in out.stdout and "other settings" in out.stderr


def test_false_safe_levels_shrink_with_the_level(tmp_path: Path, capsys, monkeypatch):
    """The false-safe and volume columns can only fall as the level rises (the same rollouts)."""
    import torch

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import false_safe_levels

    from reach.systems import MultiVehicle9D
    from training.checkpoint import save_checkpoint
    from training.network import ValueNetwork

    torch.manual_seed(0)
    save_checkpoint(tmp_path / "net.pt", ValueNetwork(MultiVehicle9D(), "ssl", width=16))
    argv = [str(tmp_path / "net.pt"), "--samples", "400", "--levels", "0,0.05,0.2"]
    assert false_safe_levels.main(argv) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 0")]
    rows = [[float(cell) for cell in line.strip("|").split("|")] for line in lines]
    assert [r[0] for r in rows] == [0, 0.05, 0.2]
    assert all(a[1] >= b[1] and a[2] >= b[2] for a, b in itertools.pairwise(rows))
    assert rows[0][2] > rows[-1][2]  # an untrained network's V spreads over these levels


def test_rows_trained_against_the_union_solve_the_pair_grid_first(tmp_path: Path, monkeypatch):
    """A run trained with --upper-bound reads the pair grid again when it resumes; on a fresh machine
    (the grid is not in the repository) the study scripts solve it before training, and only then."""
    import torch

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import nine_d_ablation as ablation
    import nine_d_layouts as layouts

    from studies import step_budget_study as study

    solve_pairwise = study.solve_pairwise
    calls: list[tuple] = []
    monkeypatch.setattr(study, "Trainer", _recording_trainer(calls))
    monkeypatch.setattr(study, "solve_pairwise", lambda path: calls.append(("groundtruth", path)))
    pairwise = tmp_path / "pair.npz"
    common = ["--out", str(tmp_path / "s"), "--pairwise", str(pairwise), "--seeds", "0"]
    assert ablation.main(["train", "--rows", "upper-bound", "--minutes", "0.01", *common]) == 0
    solve, trained = calls
    assert solve == ("groundtruth", pairwise)
    assert trained[0] == "train" and trained[2].upper_bound == str(pairwise)

    calls.clear()
    assert layouts.main(["train", "--layouts", "ssssl", "--with", "upper-bound", "--minutes", "0.01", *common]) == 0
    assert calls[0] == ("groundtruth", pairwise) and calls[1][0] == "train" and calls[1][2].layout == "ssssl"

    calls.clear()  # no row that needs it: nothing solved
    assert ablation.main(["train", "--rows", "zero-level", "--minutes", "0.01", *common]) == 0
    assert [c[0] for c in calls] == ["train"]

    calls.clear()  # already there: not solved again
    pairwise.write_bytes(b"")
    assert ablation.main(["train", "--rows", "upper-bound", "--minutes", "0.01", *common]) == 0
    assert [c[0] for c in calls] == ["train"]
    # a failed solve stops before training, with the command line's one-line error and status
    pairwise.unlink()

    def failed_solve(path: Path) -> None:
        calls.append(("groundtruth", path))
        raise ValueError("a 101x101x101 grid needs more memory than this machine has")

    monkeypatch.setattr(study, "solve_pairwise", failed_solve)
    calls.clear()
    assert ablation.main(["train", "--rows", "upper-bound", "--minutes", "0.01", *common]) == 2
    assert [c[0] for c in calls] == ["groundtruth"]

    # the grid solved is what `reach groundtruth relativepair --grid 101` solves, every 0.1 s to the horizon
    solved: list[tuple] = []

    def grid_solve(system, grid, times, **options):
        solved.append((system.name, grid, times, options))
        meta = {"scheme": {"steps": 1}, "wall_time_s": 0.0}
        return SimpleNamespace(save=Path, grid=SimpleNamespace(shape=(grid,) * 3), metadata=meta)

    monkeypatch.setattr(study, "solve", grid_solve)
    assert solve_pairwise(pairwise) == pairwise
    [(name, grid, times, options)] = solved
    from groundtruth import SolverSettings

    assert (name, grid, options) == ("relativepair", 101, {"settings": SolverSettings(dtype=torch.float32)})
    assert times[0] == 0 and all(0 < b - a <= 0.1 + 1e-9 for a, b in itertools.pairwise(times))


def test_catalogue_recipe_queue_trains_skips_what_is_done_and_resumes(tmp_path: Path, monkeypatch, capsys):
    """``benchmarks/catalogue_recipes.py run`` trains each recipe to its steps (minutes x measured rate),
    skips a finished run, and continues an unfinished one with ``reach train --resume``."""
    import importlib.util
    import json

    spec = importlib.util.spec_from_file_location("catalogue_recipes", ROOT / "benchmarks" / "catalogue_recipes.py")
    recipes = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "catalogue_recipes", recipes)  # its dataclass looks itself up there
    spec.loader.exec_module(recipes)
    from reach.systems import make_system

    for recipe in recipes.RECIPES:  # the shipped queue: registered systems, two hours of steps each
        assert recipe.steps == 120 * recipe.steps_per_minute > 0 and make_system(recipe.system).state_dim >= 6
    assert next(r for r in recipes.RECIPES if r.system == "multivehicle9d").steps == 92_400  # the shipped card's
    # each recipe's command line names its fields by their `reach train` flags (reach_cli.train.train_flags)
    nine = next(r for r in recipes.RECIPES if r.system == "multivehicle9d").command(2)
    assert nine[nine.index("--upper-bound") + 1] == "runs/pair_gt.npz" and "--upper_bound" not in nine
    from reach_cli.train import train_flags

    assert train_flags({"checkpoint_every_s": 5.0}) == ["--checkpoint-every", "5.0"]  # a flag is not always the name
    with pytest.raises(ValueError, match="no reach train option sets budget_s"):
        train_flags({"budget_s": 60.0})
    tiny = (("width", 8), ("points", 64), ("layout", "ssl"))
    monkeypatch.setattr(recipes, "ROOT", tmp_path)
    monkeypatch.setattr(recipes, "MINUTES", 2)
    monkeypatch.setattr(recipes, "RECIPES", (recipes.Recipe("tiny", "air3d", 5, "test", tiny),))
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "pair_gt.npz").write_bytes(b"")  # present: the queue does not solve it
    assert recipes.main(["run", "--threads", "1"]) == 0
    meta = tmp_path / "runs" / "catalogue" / "tiny" / "checkpoint.json"
    assert json.loads(meta.read_text())["steps"] == 10
    assert recipes.main(["run", "--threads", "1"]) == 0
    assert "tiny: done (10 steps)" in capsys.readouterr().out
    monkeypatch.setattr(recipes, "MINUTES", 3)  # a longer budget: the run resumes to 15 steps
    assert recipes.main(["run", "--threads", "1"]) == 0
    assert "train --resume" in capsys.readouterr().out
    assert json.loads(meta.read_text())["steps"] == 15
    assert recipes.main(["status"]) == 0 and "15 / 15 steps" in capsys.readouterr().out
    # --names trains only the recipes it names (a GPU session trains several at once, one process
    # each) and refuses one that is not in the queue
    other = recipes.Recipe("other", "air3d", 5, "test", tiny)
    monkeypatch.setattr(recipes, "RECIPES", (*recipes.RECIPES, other))
    assert recipes.main(["run", "--threads", "1", "--names", "tiny"]) == 0
    assert not (tmp_path / "runs" / "catalogue" / "other").exists()
    with pytest.raises(SystemExit, match="--names: no recipe 'typo'"):
        recipes.main(["run", "--names", "tiny,typo"])
    with pytest.raises(SystemExit) as refused:  # a device that does not exist here: argparse's error
        recipes.main(["run", "--names", "tiny", "--device", "tpu"])
    assert refused.value.code == 2 and "--device" in capsys.readouterr().err


def test_dimension_study_scores_snapshots_and_times_the_false_safe_goal(tmp_path: Path, monkeypatch, capsys, pair_grid):
    """``benchmarks/dimension_study.py`` scores every snapshot of a fleet's run (resumably) and reports
    the quiet minute from which its false-safe rate stays at most 0.1 % and the rates at the end,
    with a plot; a young network's near-zero rate (it calls everything unsafe) does not count."""
    import importlib.util

    from training.config import TrainConfig
    from training.trainer import Trainer

    spec = importlib.util.spec_from_file_location("dimension_study", ROOT / "benchmarks" / "dimension_study.py")
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    run = Path("runs/catalogue/multivehicle9d")
    config = TrainConfig(system="multivehicle9d", steps=4, snapshots=2, width=8, points=64, log_every=2)
    Trainer(config, tmp_path / run, progress=False).train()
    pair_grid.save(tmp_path / "pair.npz")
    monkeypatch.setattr(study, "ROOT", tmp_path)
    monkeypatch.setattr(study, "FLEETS", ((3, "multivehicle9d", run),))
    args = ["score", "--samples", "40", "--pairwise", str(tmp_path / "pair.npz")]
    assert study.main(args) == 0 and study.main(args) == 0  # the second run finds every row scored
    assert "3 cars: 2 snapshots scored" in capsys.readouterr().out
    assert study.main(["report", "--plot", "dim.png"]) == 0
    table = capsys.readouterr().out
    assert "| 3 | 9 |" in table and (tmp_path / "dim.png").stat().st_size > 0
    curve = [(5.0, 0.0, 100, 0.5), (10.0, 0.02, 100, 0.1), (15.0, 0.0005, 100, 0.05), (20.0, 0.001, 100, 0.04)]
    assert study.minutes_to_stay_below(curve) == 15.0  # not 5: the rate left the goal after it
    assert study.minutes_to_stay_below(curve[:2]) is None  # above the goal at the end


def test_certify_study_explains_how_the_closure_lost_the_set(tmp_path: Path, capsys, monkeypatch):
    """A short run prints its row, the undecided share with the part that must leave the domain, and
    the closure's rounds, whose kept shares only fall."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import certify_study

    argv = ["certify_study.py", "--levels", "0.1", "--max-seconds", "20", "--initial-splits", "2"]
    argv += ["--min-width", "0.125", "--explain", "--out-dir", str(tmp_path)]
    monkeypatch.setattr(sys, "argv", argv)
    certify_study.main()
    out = capsys.readouterr().out
    explained = [line for line in out.splitlines() if "where every input leaves the domain" in line]
    assert len(explained) == 1
    words = explained[0].split()
    undecided, leaving = float(words[words.index("undecided") + 1]), float(words[words.index("which") + 1])
    assert 0.0 <= leaving <= undecided <= 1.0
    rounds = out.splitlines()[out.splitlines().index(explained[0]) + 1].lstrip("# ").split(", ")
    kept = [float(r.split("/")[2]) for r in rounds if r]
    assert all(a >= b for a, b in itertools.pairwise(kept))
    assert (tmp_path / "level-0.1.npz").exists()


@pytest.mark.slow  # about 40 s: two tiny trainings and their scoring, on the CPU
def test_gpu_width_points_script_trains_scores_and_reports_on_a_cpu(tmp_path: Path):
    """``benchmarks/gpu_width_points.sh`` (run on a lent GPU, never by CI) trains each WIDTHxPOINTS
    variant for the wall budget, scores it, and packs the runs; ``width_points_report.py`` reads the
    unpacked runs back into one row each. Smoke size, on the CPU, for Air3D (no pair grid)."""
    import tarfile

    out, work = tmp_path / "out", tmp_path / "work"
    env = {
        **os.environ,
        "OUT": str(out),
        "WORK": str(work),
        "DEVICE": "cpu",
        "SYSTEM": "air3d",
        "BUDGET": "3",
        "SAMPLES": "200",
        "SCENARIO": "300",
        "VARIANTS": "16x256 32x512",
        "EXTRA": "--lr 0.0002 --gradient-bound off",
        "PY": sys.executable,
        "OMP_NUM_THREADS": "1",
    }
    for name, bad, shown in (("VARIANTS", "16x256 256x", "got '256x'"), ("BUDGET", "0", "got '0'")):
        refused = subprocess.run(
            ["bash", "benchmarks/gpu_width_points.sh"], cwd=ROOT, env={**env, name: bad}, capture_output=True, text=True
        )
        assert refused.returncode == 2 and shown in refused.stderr and not out.exists()  # before any work
    done = subprocess.run(["bash", "benchmarks/gpu_width_points.sh"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    summary = (out / "summary.txt").read_text()
    assert "16x256: exit 0" in summary and "32x512: exit 0" in summary and "| w32-p512 |" in summary
    unpacked = tmp_path / "unpacked"
    with tarfile.open(out / "runs.tgz.00") as tgz:
        tgz.extractall(unpacked, filter="data")
    report = subprocess.run(
        [sys.executable, "benchmarks/width_points_report.py", str(unpacked), "--json", str(tmp_path / "r.json")],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert report.returncode == 0, report.stderr
    rows = json.loads((tmp_path / "r.json").read_text())["runs"]
    assert [(r["width"], r["points"], r["budget_s"]) for r in rows] == [(16, 256, 3.0), (32, 512, 3.0)]
    assert all(r["steps"] > 0 and r["evaluation"]["samples"] == 200 for r in rows)
    config = json.loads((unpacked / "w16-p256" / "checkpoint.json").read_text())["config"]
    assert config["lr"] == 0.0002 and config["gradient_bound"] is None  # EXTRA reached every variant
    assert "| 16 | 256 | 3 |" in report.stdout
    empty = subprocess.run(
        [sys.executable, "benchmarks/width_points_report.py", str(tmp_path)], cwd=ROOT, capture_output=True, text=True
    )
    assert empty.returncode != 0 and "no run directories (w*-p*)" in empty.stderr


def test_narrowpassage_share_bounds_what_can_succeed(capsys):
    """``benchmarks/narrowpassage_share.py``: the share within reach grows with the horizon and never
    exceeds the share that starts clear; a horizon of 0 is refused by the parser."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("narrowpassage_share", ROOT / "benchmarks" / "narrowpassage_share.py")
    share = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(share)
    rows = share.shares(20_000, [0.5, 1.0, 8.0], seed=1, chunk=7_000)
    reach = [r["goal_within_reach"] for r in rows]
    clear = 1 - rows[0]["violation_at_start"]
    assert 0 < reach[0] < reach[1] < reach[2] <= clear and rows[0]["target_at_start"] <= reach[0]
    assert share.main(["--samples", "2000", "--horizons", "1"]) == 0
    assert "| 1 |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        share.main(["--horizons", "0,1"])
    assert "--horizons must be positive" in capsys.readouterr().err
