"""Bad input and faults at every public entry point: a clear error naming the value, or the documented
safe behaviour. One test (or parametrised family) per kind of finding: foreign code in files, values
that cannot be trusted, runs and tables shared between processes, interruption, wrong pairings,
validation before work, and the CLI's one-line errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import reach_envs  # noqa: F401  (registers the environments)
from reach.atomic import atomic_path
from reach.locking import LockedError, exclusive_lock, run_lock
from reach.systems import Air3D, MultiVehicle9D, RelativePair
from reach.validation import csv_floats
from reach_cli import main
from reach_envs.spaces import EpisodeOverError
from safety import SafetyFilter
from training import NeuralValueFunction, TrainConfig, Trainer, ValueNetwork, load_network, save_checkpoint

SHARED = Path(__file__).resolve().parents[2] / "shared" / "reference"
REPO = Path(__file__).resolve().parents[1]


def run_cli(*args: str) -> tuple[int, str]:
    """``reach ARGS`` in a subprocess: exit status and stderr (what a user sees)."""
    proc = subprocess.run(
        [sys.executable, "-m", "reach", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "TQDM_DISABLE": "1"},
    )
    return proc.returncode, proc.stderr


def one_line_error(code: int, err: str, *needles: str) -> None:
    """Exit 2, one line on stderr, no traceback, naming every needle."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def tiny_checkpoint(path: Path, system=None, layout: str = "ssssl") -> Path:
    torch.manual_seed(0)
    save_checkpoint(path, ValueNetwork(system or Air3D(), layout, width=8))
    return path


# ---------------------------------------------------------------------------------------- files run no code
class _Evil:
    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_pickle_is_refused_not_run(tmp_path):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.pt"
    torch.save({"format": "reach.checkpoint.v1", "metadata": {}, "model": {}, "x": _Evil(str(marker))}, evil)
    with pytest.raises(ValueError, match=r"posix\.system|Python object"):
        load_network(evil)
    code, err = run_cli("evaluate", str(evil), "--system", "air3d", "--samples", "10", "--out", str(tmp_path / "r.csv"))
    assert code == 3 and not marker.exists()  # every source failed: one error row, nothing ran (exit 3: failed in part)
    table = json.loads((tmp_path / "r.json").read_text())["results"]
    assert "not loaded" in table[0]["error"]
    # a run directory whose checkpoint is the malicious file
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(TrainConfig(steps=5).to_json())
    (run / "checkpoint.pt").write_bytes(evil.read_bytes())
    code, err = run_cli("train", "--resume", str(run))
    one_line_error(code, err, "not loaded")
    assert not marker.exists()


def test_altered_checkpoint_metadata_is_refused(tmp_path):
    path = tiny_checkpoint(tmp_path / "a.pt")
    payload = torch.load(path, weights_only=True)
    payload["metadata"]["layout"] = "rrrrl"  # same depth: the weights would fit
    torch.save(payload, path)
    with pytest.raises(ValueError, match="changed after saving"):
        load_network(path)
    with pytest.raises(ValueError, match="may not override"):
        save_checkpoint(tmp_path / "b.pt", ValueNetwork(Air3D(), "ssssl", width=8), metadata={"layout": "rrrrl"})


@pytest.mark.skipif(not (SHARED / "air3d_deepreach_ssssl_3x512.pth").exists(), reason="shared reference absent")
@pytest.mark.parametrize(("system", "layout"), [(Air3D(), "rrrrl"), (Air3D(), "ssrsl"), (RelativePair(), "ssssl")])
def test_deepreach_import_with_wrong_layout_or_system_is_refused(system, layout):
    from training import load_deepreach

    with pytest.raises(ValueError, match=r"V\(x, 0\)"):
        load_deepreach(SHARED / "air3d_deepreach_ssssl_3x512.pth", system, layout)


# ---------------------------------------------------------------------------------------- untrusted values
@pytest.mark.parametrize("t", [float("nan"), float("inf"), -5.0, 50.0, torch.tensor([0.5, float("nan")])])
def test_network_refuses_times_it_was_not_trained_for(t):
    vf = NeuralValueFunction(ValueNetwork(Air3D(), "ssssl", width=8))
    x = torch.zeros(2, 3)
    with pytest.raises(ValueError, match="lies outside"):
        vf.value(x, t)
    with pytest.raises(ValueError, match="lies outside"):
        vf.gradient(x, t)


def test_states_that_overflow_float32_are_refused(air3d_grid):
    vf = NeuralValueFunction(ValueNetwork(Air3D(), "ssssl", width=8))
    x = torch.tensor([[1e300, 0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="overflow"):
        vf.value(x, 0.5)
    for t in (float("nan"), -5.0, 50.0):
        with pytest.raises(ValueError, match="lies outside"):
            air3d_grid.value(torch.zeros(1, 3), t)


class _NaNValue:
    """A value function that answers NaN (a broken network) at every state."""

    system = Air3D()

    def value(self, x, t):
        return torch.full(x.shape[:-1], float("nan"), dtype=x.dtype)

    def gradient(self, x, t):
        return torch.full(x.shape, float("nan"), dtype=x.dtype)


def test_filter_never_passes_the_nominal_input_on_an_untrusted_value():
    x = torch.tensor([[0.9, 0.9, 0.0]])
    nominal = torch.tensor([[1.0]])
    with pytest.raises(ValueError, match="non-finite"):
        SafetyFilter(_NaNValue())(x, 1.0, nominal)
    network_filter = SafetyFilter(NeuralValueFunction(ValueNetwork(Air3D(), "ssssl", width=8)))
    for t in (float("nan"), 50.0, -1.0):
        with pytest.raises(ValueError, match="lies outside"):
            network_filter(x, t, nominal)


def test_filter_wrapper_checks_the_time_to_go_before_the_episode(tmp_path):
    from safety import SafetyFilterWrapper

    vf = NeuralValueFunction(ValueNetwork(Air3D(), "ssssl", width=8))
    with pytest.raises(ValueError, match="covers only"):
        SafetyFilterWrapper(gym.make("Air3D-v0"), vf, time_to_go=50.0)
    code, err = run_cli("filter-eval", str(tiny_checkpoint(tmp_path / "a.pt")), "--time-to-go", "50", "--episodes", "2")
    one_line_error(code, err, "covers only")


def test_rollouts_and_plots_refuse_horizons_beyond_the_value_function(tmp_path):
    ckpt = str(tiny_checkpoint(tmp_path / "a.pt"))
    code, err = run_cli("evaluate", ckpt, "--horizon", "50", "--samples", "10", "--out", str(tmp_path / "r.csv"))
    assert code == 3  # the one source is an error row naming the horizon (exit 3: failed in part)
    assert "covers only" in json.loads((tmp_path / "r.json").read_text())["results"][0]["error"]
    code, err = run_cli("plot", "slices", ckpt, "--t", "99", "--out", str(tmp_path / "s.png"))
    one_line_error(code, err, "--t 99")


# ---------------------------------------------------------------------------------------- runs and tables
def test_a_locked_run_directory_refuses_a_second_trainer(tmp_path):
    run = tmp_path / "run"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"from reach.locking import run_lock\nimport time\nwith run_lock({str(run)!r}):\n"
            "    print('held', flush=True)\n    time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        code, err = run_cli("train", "--steps", "3", "--out", str(run))
        one_line_error(code, err, "is in use by process", str(holder.pid))
        assert not (run / "config.json").exists()  # nothing was written into the locked run
    finally:
        holder.kill()
        holder.wait()
    with run_lock(run), pytest.raises(LockedError):  # also within one process
        Trainer(TrainConfig(steps=2, width=8), run, progress=False).train()


def test_a_killed_lock_holder_leaves_no_stale_lock(tmp_path):
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"from reach.locking import run_lock\nimport time\nwith run_lock({str(tmp_path)!r}):\n"
            "    print('held', flush=True)\n    time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert holder.stdout.readline().strip() == "held"
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    with run_lock(tmp_path):
        pass


def test_new_run_over_an_old_one_and_resume_changes_are_refused(tmp_path):
    run = tmp_path / "run"
    assert main(["train", "--steps", "2", "--width", "8", "--out", str(run)]) == 0
    code, err = run_cli("train", "--steps", "2", "--layout", "rrrrl", "--out", str(run))
    one_line_error(code, err, "already holds a run", "--resume")
    for option in (["--layout", "rrrrl"], ["--lr", "1e-3"], ["--points", "64"], ["--width", "16"], ["--seed", "3"]):
        code, err = run_cli("train", "--resume", str(run), *option)
        one_line_error(code, err, option[0], "cannot change")
    code, err = run_cli("train", "--resume", str(run), "--out", str(tmp_path / "other"))
    one_line_error(code, err, "not both")
    assert main(["train", "--resume", str(run), "--steps", "4"]) == 0  # stop rules may change
    # restating a stored value is not a change: the run resumes
    assert main(["train", "--resume", str(run), "--steps", "5", "--width", "8", "--layout", "ssssl"]) == 0


def test_sigint_saves_and_the_run_resumes(tmp_path):
    run = tmp_path / "run"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "reach",
            "train",
            "--steps",
            "100000",
            "--width",
            "8",
            "--points",
            "64",
            "--log-every",
            "1",
            "--checkpoint-every",
            "1000",
            "--compile",  # 100,000 steps would compile the step (10-30 s on a cold cache) before the first
            "off",  # metric line; interrupting a compiled run is not what this test checks
            "--out",
            str(run),
        ],
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "TQDM_DISABLE": "1"},
    )
    metrics = run / "metrics.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and not (metrics.exists() and len(metrics.read_text().splitlines()) >= 3):
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "--resume" in err and len(err.strip().splitlines()) == 1
    saved = json.loads((run / "checkpoint.json").read_text())["steps"]
    assert saved >= 3
    trainer = Trainer.resume(run, progress=False, steps=saved + 2)
    assert trainer.step == saved
    assert trainer.train()["steps"] == saved + 2
    steps = [json.loads(line)["step"] for line in metrics.read_text().splitlines()]
    assert steps == sorted(set(steps))  # no duplicated or lost metric lines


def test_evaluate_merges_rows_instead_of_replacing_them(tmp_path, air3d_grid):
    from safety.verification.verify import VerifySettings
    from studies.batch_verification import SourceLoading, evaluate_many

    a = str(tiny_checkpoint(tmp_path / "a.pt"))
    b = str(tiny_checkpoint(tmp_path / "b.pt", layout="rrrrl"))
    out = tmp_path / "table.csv"
    settings = VerifySettings(samples=20, scenario_samples=0)
    evaluate_many([a, b], out, settings, progress=False)
    evaluate_many([a], out, settings, progress=False)  # fewer sources: b's row stays
    evaluate_many([str(tmp_path / "missing.pt")], out, settings, loading=SourceLoading(system="air3d"), progress=False)
    rows = json.loads(out.with_suffix(".json").read_text())["results"]
    assert [Path(r["source"]).name for r in rows] == ["a.pt", "b.pt", "missing.pt"]
    assert not rows[0].get("error") and not rows[1].get("error") and rows[2]["error"]


def test_concurrent_evaluations_into_one_table_keep_every_row(tmp_path):
    sources = [str(tiny_checkpoint(tmp_path / f"{name}.pt", layout=name)) for name in ("ssssl", "rrrrl")]
    out = str(tmp_path / "table.csv")
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "reach",
                "--threads",
                "1",
                "evaluate",
                src,
                "--samples",
                "50",
                "--scenario-samples",
                "0",
                "--out",
                out,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for src in sources
    ]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    rows = json.loads(Path(out).with_suffix(".json").read_text())["results"]
    assert sorted(Path(r["source"]).name for r in rows) == ["rrrrl.pt", "ssssl.pt"]


def test_files_follow_the_umask(tmp_path):
    old = os.umask(0o002)
    try:
        with atomic_path(tmp_path / "f.json") as tmp:
            Path(tmp).write_text("{}")
    finally:
        os.umask(old)
    assert (tmp_path / "f.json").stat().st_mode & 0o777 == 0o664


def test_exclusive_lock_names_the_holder(tmp_path):
    with (
        exclusive_lock(tmp_path / "x.lock", "thing"),
        pytest.raises(LockedError, match=f"process {os.getpid()}"),
        exclusive_lock(tmp_path / "x.lock", "thing"),
    ):
        pass


# ---------------------------------------------------------------------------------------- no hang, no guess
@pytest.mark.parametrize("value", ["-1", "nan", "0", "inf"])
def test_unreachable_target_loss_is_refused(value, tmp_path):
    code, err = run_cli("train", "--target-loss", value, "--out", str(tmp_path / "r"))
    one_line_error(code, err, "--target-loss")
    with pytest.raises(ValueError, match="target_loss"):
        TrainConfig(target_loss=float(value)).validate()


def test_ground_truth_of_another_system_is_refused(tmp_path, pair_grid):
    other = tmp_path / "pair.npz"
    pair_grid.save(other)
    code, err = run_cli("train", "--steps", "2", "--groundtruth", str(other), "--out", str(tmp_path / "r"))
    one_line_error(code, err, "ground truth", "relativepair")
    assert not (tmp_path / "r").exists()
    ckpt = str(tiny_checkpoint(tmp_path / "a.pt"))
    code, err = run_cli("plot", "slices", ckpt, "--ground-truth", str(other), "--out", str(tmp_path / "s.png"))
    one_line_error(code, err, "relativepair")
    start = time.perf_counter()
    code, err = run_cli(
        "sweep",
        "--layouts",
        "ssssl",
        "--seeds",
        "1",
        "--steps",
        "5",
        "--groundtruth",
        str(other),
        "--out",
        str(tmp_path / "sweep"),
    )
    one_line_error(code, err, "relativepair")
    assert time.perf_counter() - start < 60 and not (tmp_path / "sweep" / "runs").exists()


# ---------------------------------------------------------------------------------------- the CLI boundary
@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["train", "--device", "cuda" if not torch.cuda.is_available() else "cuda:99", "--out", "r"], ["--device"]),
        (["train", "--device", "tpu", "--out", "r"], ["tpu"]),
        (["train", "--checkpoint-every", "nan", "--steps", "2", "--out", "r"], ["--checkpoint-every", "nan"]),
        (["train", "--seed", "-1", "--out", "r"], ["--seed", "-1"]),
        (["filter-eval", "--seed", "-1"], ["--seed", "-1"]),
        (["filter-eval", "--thresholds", "0,nan"], ["--thresholds"]),
        (["filter-eval", "--time-to-go", "-3"], ["--time-to-go"]),
        (["record", "--seed", "-1"], ["--seed"]),
        (["record", "--every", "0"], ["--every", "0"]),
        (["record", "NoSuchEnv-v0"], ["NoSuchEnv-v0"]),
        (["sweep", "--train", "bogus=1", "--steps", "2", "--out", "sw"], ["bogus"]),
        (["sweep", "--workers", "0", "--out", "sw"], ["--workers"]),
        (["demo", "--samples", "0"], ["--samples"]),
        (["demo", "--budget", "nan"], ["duration"]),
        (["evaluate", "x.pt", "--beta", "2"], ["--beta"]),
        (["evaluate", "x.pt", "--target-eps", "0"], ["--target-eps"]),
        (["evaluate", "x.pt", "--robust-samples", "-1"], ["--robust-samples"]),
        (["evaluate", "x.pt", "--policy", "greedyy"], ["--policy", "greedyy"]),
        (["filter-eval", "--policy", "greedyy"], ["--policy", "greedyy"]),
        (["filter-eval", "--filters", "switch,bogus"], ["--filters", "bogus"]),
        (["filter-eval", "--filters", "smooth", "--gammas", "-1"], ["--gammas"]),
        (["groundtruth", "air3d", "--grid", "1000", "--out", "g.npz"], ["GiB"]),
        (["groundtruth", "air3d", "--grid", "3", "--out", "g.npz"], ["--grid"]),
        (["groundtruth", "nosuchsystem", "--out", "g.npz"], ["nosuchsystem"]),
        (["groundtruth", "air3d", "--grid", "21", "--out", "/etc/passwd/x.npz"], ["/etc/passwd"]),
        (["groundtruth", "air3d", "--grid", "21", "--times", "0.5,0.2", "--out", "g.npz"], ["--times"]),
        (["groundtruth", "air3d", "--grid", "21", "--times", "0,0.3,...,1.1", "--out", "g.npz"], ["--times", "1.1"]),
        (["filter-eval", "--thresholds", "0,0.01,...,inf"], ["--thresholds", "inf"]),
        (["bogus-command"], ["bogus-command"]),
    ],
)
def test_cli_errors_are_one_line_naming_the_value(args, needles, tmp_path, capsys):
    """In-process (a subprocess per case would cost seconds of interpreter start-up each); the
    subprocess tests above show the same boundary from outside."""
    start = time.perf_counter()
    try:
        code = main([a if a not in ("r", "sw", "g.npz") else str(tmp_path / a) for a in args])
    except SystemExit as exit_:  # argparse's usage errors leave through SystemExit
        code = exit_.code
    one_line_error(code, capsys.readouterr().err, *needles)
    assert time.perf_counter() - start < 60  # refused before any work


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("0,0.05,...,1.1", [round(0.05 * k, 12) for k in range(23)]),
        ("0,0.1,...,1.0", [round(0.1 * k, 12) for k in range(11)]),
        ("0.5,1,...,2", [0.5, 1.0, 1.5, 2.0]),
        ("0,0.1,...,0.1", [0.0, 0.1]),
        ("0.2,0.5,1", [0.2, 0.5, 1.0]),
    ],
)
def test_number_lists_take_an_arithmetic_progression(text, expected):
    """The docs write output times as ``0,0.05,...,1.1``; each term is exact to round-off and the
    last is the number written."""
    values = csv_floats("--times", text)
    assert values == pytest.approx(expected, abs=1e-12)
    assert values[-1] == float(text.split(",")[-1])


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("0,0.3,...,1", "whole number of steps"),  # the step does not reach the last term
        ("1,0.5,...,0", "must be positive"),
        ("0,...,1", "FIRST,SECOND,...,LAST"),
        ("0,0.1,...", "FIRST,SECOND,...,LAST"),
        ("0,0.1,...,0.5,...,1", "FIRST,SECOND,...,LAST"),
        ("0,0.1,...,nan", "nan"),
        ("0,1e-9,...,1", "at most"),  # refused before a billion numbers are made
    ],
)
def test_a_malformed_progression_is_refused_naming_it(text, needle):
    with pytest.raises(ValueError, match="--times") as err:
        csv_floats("--times", text)
    assert needle in str(err.value)


def test_debug_shows_the_traceback(tmp_path):
    code, err = run_cli("--debug", "train", "--steps", "2", "--out", str(tmp_path / "r"), "--system", "nosuch")
    assert code != 0 and "Traceback" in err and "nosuch" in err


def test_corrupt_sources_become_error_rows(tmp_path):
    good = str(tiny_checkpoint(tmp_path / "good.pt"))
    (tmp_path / "empty.npz").write_bytes(b"")
    np.savez(tmp_path / "full.npz", values=np.zeros(3))
    (tmp_path / "truncated.npz").write_bytes((tmp_path / "full.npz").read_bytes()[:40])
    nosys = tmp_path / "nosystem.pt"
    payload = torch.load(good, weights_only=True)
    del payload["metadata"]["system"]
    torch.save(payload, nosys)
    os.symlink(tmp_path / "loop_b", tmp_path / "loop_a")
    os.symlink(tmp_path / "loop_a", tmp_path / "loop_b")
    sources = [good, *(str(tmp_path / n) for n in ("empty.npz", "truncated.npz", "nosystem.pt", "loop_a"))]
    out = tmp_path / "r.csv"
    # the good source's row is written; the command says that 4 of 5 failed, with a non-zero status
    assert main(["evaluate", *sources, "--samples", "20", "--scenario-samples", "0", "--out", str(out)]) == 3
    rows = {Path(r["source"]).name: r for r in json.loads(out.with_suffix(".json").read_text())["results"]}
    assert not rows["good.pt"].get("error")
    for name in ("empty.npz", "truncated.npz", "nosystem.pt", "loop_a"):
        assert rows[name]["error"], name


def test_default_groundtruth_output_serves_rollouts(tmp_path):
    out = tmp_path / "g.npz"
    assert main(["groundtruth", "air3d", "--grid", "21", "--compile", "off", "--out", str(out)]) == 0
    from groundtruth import GridSolution

    solution = GridSolution.load(out)
    assert solution.time_range == (0.0, pytest.approx(Air3D().horizon))
    assert len(solution.times) >= 11
    code = main(["evaluate", str(out), "--samples", "20", "--scenario-samples", "0", "--out", str(tmp_path / "r.csv")])
    assert code == 0


# ---------------------------------------------------------------------------------------- environments
def test_env_refuses_steps_outside_an_episode_and_unknown_options():
    env = gym.make("Air3D-v0", disturbance=None).unwrapped
    with pytest.raises(EpisodeOverError, match="before reset"):
        env.step(np.zeros(1))
    with pytest.raises(ValueError, match="sate"):
        env.reset(options={"sate": [0.5, 0.5, 0.0]})
    env.reset(seed=0, options={"state": [0.6, 0.0, 3.0]})  # pursuer ahead, heading back: collides
    terminated = truncated = False
    while not (terminated or truncated):
        _, _, terminated, truncated, _ = env.step(np.zeros(1))
    with pytest.raises(EpisodeOverError, match=r"terminated|truncated"):
        env.step(np.zeros(1))
    env.reset(seed=0)
    env.step(np.zeros(1))  # a reset starts over


def test_vector_env_refuses_unknown_options():
    venv = gym.make_vec("Air3D-v0", num_envs=2, vectorization_mode="vector_entry_point")
    with pytest.raises(ValueError, match="reset_maks"):
        venv.reset(options={"reset_maks": [True, False]})


def test_pettingzoo_reset_reports_collision_truthfully():
    from reach_envs.parallel import parallel_env

    penv = parallel_env("three-car-9d")
    system = MultiVehicle9D()
    state = np.zeros(system.state_dim)
    state[:6] = [0.0, 0.0, 0.1, 0.0, 0.8, 0.8]  # cars 1 and 2 overlap
    _, infos = penv.reset(seed=0, options={"state": state})
    assert infos["car_1"]["collision"] and infos["car_2"]["collision"] and not infos["car_3"]["collision"]
    with pytest.warns(UserWarning, match="unknown reset option"):
        penv.reset(seed=0, options={"sate": state})


def test_a_pettingzoo_action_of_the_wrong_size_names_its_agent():
    from reach_envs.parallel import parallel_env

    penv = parallel_env(system="narrowpassage")  # two drivers, each acting (a, psi)
    penv.reset(seed=0)
    actions = {agent: np.zeros(2, dtype=np.float32) for agent in penv.agents}
    actions["car_2"] = np.zeros(3, dtype=np.float32)
    with pytest.raises(ValueError, match=r"agent 'car_2': action must have shape \(2,\), got shape \(3,\)"):
        penv.step(actions)


def test_an_interrupt_anywhere_is_one_line_and_exit_130(monkeypatch, capsys):
    import reach_cli.envs as envs_command

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(envs_command, "run", interrupted)  # main builds its parser, so it picks this up
    assert main(["envs"]) == 130
    assert capsys.readouterr().err.strip() == "reach envs: interrupted"


@pytest.mark.parametrize(
    "field, value",
    [
        ("chunk_size", 0),
        ("chunk_size", True),
        ("chunk_size", 2.5),
        ("dt", 0.0),
        ("dt", float("nan")),
        ("dt", -0.01),
        ("horizon", -1.0),
        ("horizon", float("inf")),
        ("integrator", "bogus"),
    ],
)
def test_verify_settings_refuse_bad_rollout_settings_by_name(field, value):
    """The library path has no argparse in front of it: a verification refuses a setting that would
    stall, divide by zero or roll out with an unknown integrator before any rollout starts."""
    from safety.verification.verify import VerifySettings

    with pytest.raises(ValueError, match=field):
        VerifySettings(**{field: value})
    VerifySettings(**{field: {"chunk_size": 7, "dt": 0.01, "horizon": 0.5, "integrator": "rk4"}[field]})


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"goal": (float("nan"), 0.0)}, r"DubinsReachAvoid: goal must be finite"),
        ({"goal": (0.7, 0.0, 0.3)}, r"DubinsReachAvoid: goal must have 2 coordinates, got 3"),
        ({"goal": "ab"}, r"DubinsReachAvoid: goal must be a sequence of 2 real numbers, got 'ab'"),
        ({"obstacle": (0.1, "x")}, r"DubinsReachAvoid: obstacle\[1\] must be a real number, got 'x'"),
        ({"obstacle": (0.1, float("inf"))}, r"DubinsReachAvoid: obstacle must be finite"),
    ],
)
def test_a_point_parameter_of_the_wrong_length_type_or_value_is_refused_by_name(keywords, message):
    """A NaN goal made every state "in the goal" on the torch backend (hypot hides the NaN); a 3-tuple
    lost its third value; 'ab' gave a float-conversion message."""
    from reach.systems import DubinsReachAvoid

    with pytest.raises(ValueError, match=message):
        DubinsReachAvoid(**keywords)
    assert DubinsReachAvoid(goal=np.array([0.5, 0.1])).goal == (0.5, 0.1)


def test_a_non_finite_input_the_filter_computed_never_blames_the_callers_action(monkeypatch):
    """The wrapper checks the caller's action, then the filter's own input: a NaN the filter computed
    (here planted in its decision) is refused saying the nominal action was not the cause."""
    import torch

    from safety import SafetyFilterWrapper

    env = SafetyFilterWrapper(gym.make("Air3D-v0"))
    env.reset(seed=0)
    adapter = env._adapter

    def nan_decision(x, elapsed, u_nominal):
        _, info = type(adapter)._decide(adapter, x, elapsed, u_nominal)
        return torch.full_like(u_nominal, float("nan")), info

    monkeypatch.setattr(adapter, "_decide", nan_decision)
    with pytest.raises(ValueError, match=r"the safety filter computed a non-finite input .* not the cause"):
        env.step(np.zeros(1, dtype=np.float32))
    with pytest.raises(ValueError, match="action contains a non-finite value"):  # the caller's own NaN
        env.step(np.full(1, np.nan, dtype=np.float32))
