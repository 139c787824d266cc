"""studies.train_until: phases of training, each verified on fresh states, whose wrong claims become
training points, until the scenario bound holds or the budget ends; resumable; the final bound on
states no phase drew. A tiny network on Air3D, so that every test takes seconds."""

from __future__ import annotations

import json
import signal
from dataclasses import replace

import pytest
import torch

from reach_cli import main
from safety.verification.refuted import refuted_points
from safety.verification.rollout import RolloutSettings, rollout
from safety.verification.verify import sample_states
from studies.train_until import TrainUntilSettings, _verified, final_seed, phase_seed, train_until
from training import TrainConfig, Trainer, TrainingInterrupted
from training.loss import Anchors, RefutedPoints, loss_terms
from training.network import NeuralValueFunction

CONFIG = TrainConfig(system="air3d", width=16, points=256, log_every=1000, checkpoint_every_s=0.0, seed=0)
#: small verifications with a coarse step; a target no tiny network meets
SETTINGS = TrainUntilSettings(
    phase_steps=40, max_phases=2, samples=300, scenario_samples=100, dt=0.01, target_eps=1e-6, seed=3
)


def _phases(run):
    return json.loads((run / "phases.json").read_text())


def test_settings_refuse_bad_values_naming_them():
    bad = [("phase_steps", 0), ("target_eps", 1.5), ("hard_fraction", 1.0), ("samples", True)]
    bad += [("refuted_weight", -1.0), ("refuted_margin", float("nan")), ("refuted_per_trajectory", 0)]
    for name, value in bad:
        with pytest.raises(ValueError, match=name):
            replace(SETTINGS, **{name: value})
    with pytest.raises(ValueError, match="dt"):
        TrainUntilSettings(dt=-1.0)


def test_planted_errors_are_found_and_phases_reduce_them(tmp_path):
    run = tmp_path / "run"
    trainer = Trainer(replace(CONFIG, steps=1), run, progress=False)
    with torch.no_grad():  # planted: the network claims safe far into the collision set
        trainer.network.output.bias += 0.5
    trainer.run.write_config(trainer.config)
    trainer.checkpointer.save(0, 0.0, None, None)
    vs = SETTINGS.verify_settings(phase_seed(SETTINGS.seed, 0), "avoid")
    planted, wrong, _ = _verified(trainer, vs, tmp_path / "s")
    assert planted["false_safe_rate"] > 0.05 and wrong.shape[0] == round(planted["false_safe_rate"] * 300)
    # the hard states' sampling alone (the refuted points' term has a test of its own, below)
    record = train_until(CONFIG, run, replace(SETTINGS, phase_steps=150, refuted_weight=0.0), progress=False)
    phases = record["phases"]
    assert [p["phase"] for p in phases] == [0, 1] and record["stopped"] == "budget"
    assert all(p["hard_states_added"] == round(p["verification"]["false_safe_rate"] * 300) for p in phases)
    assert phases[-1]["verification"]["false_safe_rate"] < planted["false_safe_rate"] / 2
    hard = torch.load(run / "hard" / "phase-000.pt")
    assert hard.shape == (phases[0]["hard_states_added"], 3)


def _planted(run):
    """A run whose network claims safe far into the collision set (its output raised by 0.5)."""
    trainer = Trainer(replace(CONFIG, steps=1), run, progress=False)
    with torch.no_grad():
        trainer.network.output.bias += 0.5
    trainer.run.write_config(trainer.config)
    trainer.checkpointer.save(0, 0.0, None, None)
    return trainer


def test_refuted_points_lie_on_failed_rollouts_before_their_failure(tmp_path):
    trainer = _planted(tmp_path / "run")
    vf = NeuralValueFunction(trainer.network.eval())
    settings = RolloutSettings(dt=0.01, policy="greedy").for_system(trainer.system)
    states = sample_states(trainer.system, 400, 5)
    result = rollout(vf, states, settings, record=True, progress=False)
    x, t = refuted_points(result, settings, per_trajectory=4)
    failed = result.failed & (result.decided_time > 0)
    assert 0 < x.shape[0] <= 4 * int(failed.sum()) and x.shape == (t.shape[0], 3)
    # the first point of each failed rollout is its start, at the full horizon
    starts = t == settings.horizon
    assert int(starts.sum()) == int(failed.sum())
    assert torch.equal(x[starts], states[failed].to(x.dtype))
    assert bool(((t > 0) & (t <= settings.horizon)).all())
    # the defining property: from each point, with its time-to-go, the same policy fails again (a
    # rollout restarted mid-way rounds its times differently, so a tie may go the other way)
    again = rollout(vf, x, replace(settings, horizon=None), progress=False, horizon=float(t.max()))
    fails = [
        bool(rollout(vf, x[i : i + 1], settings, horizon=float(t[i]), progress=False).failed[0])
        for i in range(0, x.shape[0], max(1, x.shape[0] // 40))
    ]
    assert again.num_states == x.shape[0] and sum(fails) >= 0.95 * len(fails)
    with pytest.raises(ValueError, match="recorded"):
        refuted_points(rollout(vf, states[:5], settings, progress=False), settings, 4)
    with pytest.raises(ValueError, match="per_trajectory"):
        refuted_points(result, settings, 0)


def test_the_refuted_term_is_what_the_loss_adds_and_it_lowers_the_claims(tmp_path):
    trainer = _planted(tmp_path / "run")
    net = trainer.network
    x = sample_states(trainer.system, 64, 2)
    t = torch.rand(64)
    margin, weight = 0.05, 3.0
    base, _ = loss_terms(net, x, t, pde=False)
    total, terms = loss_terms(net, x, t, pde=False, anchors=Anchors(refuted=RefutedPoints(x, t, 1.0, margin, weight)))
    expected = torch.relu(net(x, t) + margin).mean()
    assert torch.allclose(terms["refuted"], expected) and torch.allclose(total, base + weight * expected)
    _, reach = loss_terms(net, x, t, pde=False, anchors=Anchors(refuted=RefutedPoints(x, t, -1.0, 0.0, 1.0)))
    assert torch.allclose(reach["refuted"], torch.relu(-net(x, t)).mean())
    # the sampler draws hard_fraction of a step's points among those the curriculum has reached
    sampler = trainer.sampler
    sampler.hard_fraction = 0.25
    sampler.refuted = RefutedPoints(x, torch.linspace(0, 1, 64), 1.0, 0.0, 1.0)
    batch = sampler.refuted_batch(0.5)
    assert batch.x.shape == (64, 3) and bool((batch.t <= 0.5).all())
    assert sampler.refuted_batch(-1.0) is None


def test_a_phase_trained_on_refuted_points_stops_claiming_there(tmp_path):
    loop = replace(SETTINGS, phase_steps=150, max_phases=2)
    for weight in (0.0, 10.0):
        _planted(tmp_path / f"w{weight}")
        train_until(CONFIG, tmp_path / f"w{weight}", replace(loop, refuted_weight=weight), progress=False)
    # phase 0 is the same in both runs (no points yet): the points it found, which only the
    # weighted run records, are where phase 1 trained differently
    points = torch.load(tmp_path / "w10.0" / "hard" / "phase-000-refuted.pt", weights_only=True)
    assert points["x"].shape[0] > 0 and points["x"].shape[0] == points["t"].shape[0]
    assert torch.load(tmp_path / "w0.0" / "hard" / "phase-000-refuted.pt", weights_only=True)["x"].shape[0] == 0
    claims = {}
    for weight in (0.0, 10.0):
        net = Trainer.resume(tmp_path / f"w{weight}", progress=False).network.eval()
        with torch.no_grad():
            claims[weight] = float((net(points["x"], points["t"]) > 0).float().mean())
    # side by side from the same planted network: only the term differs
    assert claims[10.0] < 0.5 * claims[0.0], claims


def test_stops_at_an_easy_target(tmp_path):
    easy = replace(SETTINGS, target_eps=0.9, max_wrong_rate=1.0, max_phases=5)
    record = train_until(CONFIG, tmp_path / "run", easy, progress=False)
    assert record["stopped"] == "target" and len(record["phases"]) == 1 and record["phases"][0]["holds"]
    assert record["final"]["steps"] == 40


def test_stops_at_the_wall_budget(tmp_path):
    record = train_until(CONFIG, tmp_path / "run", replace(SETTINGS, max_phases=5, budget_s=1e-3), progress=False)
    assert record["stopped"] == "budget" and len(record["phases"]) == 1 and not record["final"]["holds"]


def test_sampler_mixes_points_near_the_hard_states(tmp_path):
    trainer = Trainer(replace(CONFIG, steps=1), tmp_path / "run", progress=False)
    sampler = trainer.sampler
    sampler.hard_states = torch.tensor([[0.1, -0.2, 0.3]])
    sampler.hard_fraction, sampler.hard_radius = 0.25, 0.01
    x, _, _ = sampler.points(1.0)
    span = sampler._span
    near = ((x - sampler.hard_states).abs() <= 0.01 * span + 1e-6).all(dim=1)
    assert int(near[:64].sum()) == 64 and int(near[64:].sum()) < 5


def test_resumes_after_an_interruption_without_repeating_a_phase(tmp_path):
    run = tmp_path / "run"
    first = train_until(CONFIG, run, SETTINGS, progress=False, stop_after_phases=1)
    assert len(first["phases"]) == 1 and first["final"] is None
    Trainer.resume(run, progress=False, steps=55).train()  # killed in the middle of phase 1
    record = train_until(CONFIG, run, SETTINGS, progress=False)
    assert [p["steps"] for p in _phases(run)["phases"]] == [40, 80] and _phases(run)["final"] is not None
    assert [p["phase"] for p in record["phases"]] == [0, 1]
    assert [p["steps"] for p in record["phases"]] == [40, 80]
    assert record["phases"][0] == first["phases"][0]
    with pytest.raises(ValueError, match="other settings"):
        train_until(CONFIG, run, replace(SETTINGS, samples=301), progress=False)


def test_a_record_written_before_a_setting_existed_continues_at_its_default(tmp_path):
    run = tmp_path / "run"
    train_until(CONFIG, run, SETTINGS, progress=False, stop_after_phases=1)
    record = _phases(run)
    for name in ("refuted_weight", "refuted_margin", "refuted_per_trajectory", "max_refuted_points"):
        del record["settings"][name]  # as an older loop wrote it
    (run / "phases.json").write_text(json.dumps(record))
    with pytest.raises(ValueError, match="other settings"):  # the new setting away from its default
        train_until(CONFIG, run, replace(SETTINGS, refuted_weight=1.0), progress=False)
    done = train_until(CONFIG, run, SETTINGS, progress=False)
    assert [p["steps"] for p in done["phases"]] == [40, 80] and done["settings"]["refuted_weight"] == 0.0


def test_resumes_after_sigint_in_the_middle_of_a_phase(tmp_path, monkeypatch):
    run = tmp_path / "run"
    optimise = Trainer._optimise

    def interrupted(self):  # a real SIGINT, delivered to this process at step 55 (in phase 1)
        record = optimise(self)
        if self.step == 55:
            signal.raise_signal(signal.SIGINT)
        return record

    monkeypatch.setattr(Trainer, "_optimise", interrupted)
    with pytest.raises(TrainingInterrupted):
        train_until(CONFIG, run, SETTINGS, progress=False)
    monkeypatch.undo()
    assert [p["steps"] for p in _phases(run)["phases"]] == [40] and _phases(run)["final"] is None
    assert Trainer.resume(run, progress=False).step == 55
    record = train_until(CONFIG, run, SETTINGS, progress=False)
    assert [p["steps"] for p in record["phases"]] == [40, 80] and record["final"]["steps"] == 80


def test_final_bound_uses_states_no_phase_drew(tmp_path):
    record = train_until(CONFIG, tmp_path / "run", SETTINGS, progress=False)
    seeds = {p["seed"] for p in record["phases"]}
    final = record["final"]["seed"]
    assert final == final_seed(SETTINGS.seed) and final not in seeds
    # every verification draws from seeds s..s+3: the final block meets no phase's, for any number of phases
    blocks = [set(range(phase_seed(SETTINGS.seed, i), phase_seed(SETTINGS.seed, i) + 4)) for i in range(1000)]
    assert all(not (set(range(final, final + 4)) & b) for b in blocks)
    system = Trainer.resume(tmp_path / "run", progress=False).system
    states = sample_states(system, 300, final)
    assert not any(torch.equal(states, sample_states(system, 300, s)) for s in seeds)


def test_cli_bad_input_is_one_line_exit_2(capsys):
    for flag, value in [("--target-eps", "-1"), ("--refuted-weight", "-1"), ("--refuted-margin", "nan")]:
        with pytest.raises(SystemExit) as exit_info:
            main(["train-until", "--out", "unused", flag, value])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and flag in err


def test_cli_trains_until_and_records_the_phases(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["--system", "air3d", "--width", "16", "--points", "256", "--phase-steps", "20", "--max-phases", "1"]
    assert main(["train-until", "--out", str(out), *args, "--samples", "100", "--dt", "0.01"]) == 0
    assert "1 phases, stopped at the budget" in capsys.readouterr().out
    assert [p["steps"] for p in _phases(out)["phases"]] == [20] and not (out / "verify-store").exists()


def test_cli_takes_the_recipe_options_of_reach_train_and_refuses_changing_them_on_a_continued_run(
    tmp_path, capsys
):
    out = tmp_path / "run"
    recipe = ["--system", "air3d", "--width", "16", "--points", "256", "--lr", "3e-4", "--zero-level-fraction", "0.1"]
    loop = ["--phase-steps", "10", "--max-phases", "1", "--samples", "100", "--dt", "0.01"]
    assert main(["train-until", "--out", str(out), *recipe, *loop]) == 0
    stored = Trainer.resume(out, progress=False).config
    assert stored.lr == 3e-4 and stored.zero_level_fraction == 0.1 and stored.width == 16
    capsys.readouterr()
    assert main(["train-until", "--out", str(out), *recipe, *loop]) == 0  # the same recipe continues it
    changed = [*recipe[:-4], "--lr", "1e-3", "--zero-level-fraction", "0.1"]
    assert main(["train-until", "--out", str(out), *changed, *loop]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--lr 0.001" in err and "stored: 0.0003" in err
    with pytest.raises(SystemExit):  # each phase sets its steps: no --steps
        main(["train-until", "--out", str(out), "--steps", "5"])
