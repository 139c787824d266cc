"""The shipped value networks: each loads, fits its envs' physics, and reproduces its card's rates."""

from __future__ import annotations

import json
import math
import shutil

import gymnasium as gym
import pytest

import reach_envs
from reach_cli import main
from safety.filters.wrappers import SafetyFilterWrapper
from safety.value_loading import load_value_function
from safety.verification.metrics import wilson_interval
from safety.verification.verify import VerifySettings, sample_states, verify
from training import pretrained

NAMES = pretrained.names()
#: states per model in the card check: sampling error, not the card's 100k, sets the tolerance
SMALL_SAMPLE = {"air3d": 3000}
DEFAULT_SMALL_SAMPLE = 1000
#: the Wilson interval's z: 4 sigma, so a true card fails by chance about once in 16,000 checks
Z = 4.0


def test_every_registered_env_has_a_shipped_model() -> None:
    for env_id, scene in reach_envs.ENV_SCENES.items():
        system = gym.make(env_id).unwrapped.system
        (card,) = [c for c in pretrained.cards() if env_id in c.env_ids]
        source = pretrained.for_env(env_id, system, allow_untrusted=not card.verdict.passes)
        assert source == (card.filter_source or pretrained.PREFIX + card.name), (env_id, scene)


@pytest.mark.parametrize("name", NAMES)
def test_model_loads_and_fits_its_envs(name: str) -> None:
    card = pretrained.card(name)
    loaded = load_value_function(pretrained.PREFIX + name, system=card.system)
    assert loaded.label == pretrained.PREFIX + name
    assert loaded.kind == {"network": "reach", "grid": "grid"}[card.format]
    assert loaded.layout == card.training["layout"]
    # package data: networks of a few hundred KB, a compact grid of a few MB
    assert pretrained.checkpoint_path(name).stat().st_size < {"network": 1_000_000, "grid": 8_000_000}[card.format]
    if card.filter_source:  # what the card's envs filter with loads, and is built on the model
        assert pretrained.PREFIX + name in card.filter_source
        assert load_value_function(card.filter_source, system=card.system).value_function.system.same_physics(
            loaded.value_function.system
        )
    for env_id in card.env_ids:
        env = gym.make(env_id)
        assert env.unwrapped.system.same_physics(loaded.value_function.system), env_id
        trusted = card.verdict.passes
        if not trusted:  # nothing picks an untrusted model: refused, naming the figures and the opt-in
            with pytest.raises(ValueError, match=r"fails \(.*allow_untrusted=True"):
                SafetyFilterWrapper(gym.make(env_id))
        # no value function: the shipped one for this env (opted in where it fails the bar)
        filtered = SafetyFilterWrapper(env, allow_untrusted=not trusted)
        filtered.reset(seed=0)
        _, _, _, _, info = filtered.step(filtered.action_space.sample())
        assert math.isfinite(info["filter_value"])
        assert info["filter_source_trusted"] is trusted and filtered.source_verdict == card.verdict
        assert filtered.safety_filter.value_function.system.same_physics(env.unwrapped.system)


@pytest.mark.parametrize("name", NAMES)
def test_model_reproduces_its_card(name: str) -> None:
    """A fresh sample (another seed than the card's) lands within 4-sigma Wilson intervals of every
    rate on the card: the file ships what the card measured."""
    card = pretrained.card(name)
    metrics = card.metrics
    assert metrics, f"{name}: the card has no evaluation; run benchmarks/make_pretrained.py evaluate {name}"
    vf = load_value_function(pretrained.PREFIX + name).value_function
    n = SMALL_SAMPLE.get(name, DEFAULT_SMALL_SAMPLE)
    settings = VerifySettings(samples=n, scenario_samples=0, robust_samples=0, seed=card.evaluation["seed"] + 7919)
    row = verify(vf, sample_states(vf.system, n, settings.seed), settings, progress=False)
    # false safe is an avoid problem's wrong claim, false reachable a reach or reach-avoid problem's
    keys = ("violation_rate", "false_safe_rate", "false_reachable_rate", "failure_rate", "collision_rate")
    rates = [k for k in keys if k in metrics]
    # a pure reach problem has no failure set, so no collisions to count
    required = {"violation_rate"} | ({"collision_rate"} if vf.system.kind != "reach" else set())
    assert required <= set(rates), f"{name}: the card lacks rates: {sorted(metrics)}"
    for key in rates:
        low, high = wilson_interval(round(row[key] * n), n, z=Z)
        assert low <= metrics[key] <= high, f"{name}: {key} {row[key]:.4f} on {n} states, card {metrics[key]:.4f}"


#: (name, index) of every evaluation a card records besides its main one
ALSO_EVALUATED = [(c.name, i) for c in pretrained.cards() for i in range(len(c.also_evaluated))]


@pytest.mark.slow  # about 25 s (the 9D card's three other evaluations): run by name in .ci/run's slow step
@pytest.mark.parametrize(("name", "index"), ALSO_EVALUATED)
def test_model_reproduces_its_other_evaluations(name: str, index: int, pair_grid, tmp_path) -> None:
    """Each evaluation a card records besides its main one (capped by the union of pairwise BRTs,
    rolled out under the greedy policy) lands within 4-sigma Wilson intervals of its rates on a fresh
    sample, with its recorded source and policy. A grid member of the source (the card's 101^3 pair
    grid, not package data) is the tests' 45^3 pair grid: it moves V only where the union is below
    the network."""
    from safety.value_loading import composition_kind, member_sources

    card = pretrained.card(name)
    other = card.also_evaluated[index]
    source, metrics = other["source"], other["metrics"]
    kind = composition_kind(source)
    members = member_sources(source)
    assert pretrained.PREFIX + name in members, source
    if any(m.endswith(".npz") for m in members):
        assert card.system == "multivehicle9d", "the tests' pair grid is the 9D system's"
        pair_grid.save(tmp_path / "pair.npz")
        members = [str(tmp_path / "pair.npz") if m.endswith(".npz") else m for m in members]
    vf = load_value_function(f"{kind}:{','.join(members)}" if kind else members[0]).value_function
    n = SMALL_SAMPLE.get(name, DEFAULT_SMALL_SAMPLE)
    seed = other["seed"] + 7919
    settings = VerifySettings(samples=n, scenario_samples=0, robust_samples=0, seed=seed, policy=other["policy"])
    row = verify(vf, sample_states(vf.system, n, seed), settings, progress=False)
    for key in ("violation_rate", "false_safe_rate", "collision_rate"):
        low, high = wilson_interval(round(row[key] * n), n, z=Z)
        assert low <= metrics[key] <= high, (
            f"{other['label']}: {key} {row[key]:.4f} on {n} states, card {metrics[key]:.4f}"
        )


def test_unknown_and_tampered_models_are_refused(tmp_path, monkeypatch) -> None:
    with pytest.raises(ValueError, match=r"no pretrained model 'nope'.*air3d"):
        load_value_function("pretrained:nope")
    for f in pretrained.DIRECTORY.glob("air3d.*"):
        shutil.copy(f, tmp_path / f.name)
    monkeypatch.setattr(pretrained, "DIRECTORY", tmp_path)
    weights = bytearray((tmp_path / "air3d.pt").read_bytes())
    weights[-100] ^= 0xFF
    (tmp_path / "air3d.pt").write_bytes(bytes(weights))
    with pytest.raises(ValueError, match="not the file its model card describes"):
        load_value_function("pretrained:air3d")
    (tmp_path / "air3d.pt").unlink()
    with pytest.raises(ValueError, match="missing"):
        load_value_function("pretrained:air3d")
    card = json.loads((tmp_path / "air3d.card.json").read_text())
    (tmp_path / "air3d.card.json").write_text(json.dumps({**card, "format": "pickle"}))
    with pytest.raises(ValueError, match=r"format must be one of \['grid', 'network'\], got 'pickle'"):
        load_value_function("pretrained:air3d")


def test_env_without_a_shipped_model_needs_a_value_function() -> None:
    """Every built-in system ships a model, so a system of other parameters (other physics) is the
    env no model fits: the shipped Dubins3D model is not used for a faster car."""
    from reach.systems import Dubins3D

    env = reach_envs.make_env(Dubins3D(velocity=0.9), dt=0.02)
    assert any(c.system == "dubins3d" for c in pretrained.cards())
    with pytest.raises(ValueError, match=r"no pretrained value function for env .*pass a value function"):
        SafetyFilterWrapper(env)


def test_cli_lists_cards_and_evaluates_a_shipped_model(capsys, tmp_path) -> None:
    assert main(["pretrained"]) == 0
    listing = capsys.readouterr().out
    for name in NAMES:
        assert f"pretrained:{name}" in listing
    assert main(["pretrained", "nope"]) == 2
    assert "no pretrained model 'nope'" in capsys.readouterr().err
    out = tmp_path / "eval.csv"
    assert main(["evaluate", "pretrained:air3d", "--samples", "300", "--scenario-samples", "0", "--out", str(out)]) == 0
    assert "pretrained:air3d" in out.read_text()


def test_starts_outside_the_learned_brt_come_from_the_scene() -> None:
    """--start-from scene keeps the scene's own starts (a merge stays a merge) that lie in {V > margin}."""
    import numpy as np
    import torch

    from reach_envs.scenes import make_scene
    from safety.verification.verify import values_at
    from studies.filter_episodes import outside_states

    vf = load_value_function("pretrained:multivehicle9d").value_function
    scene = make_scene("three-car-merge")
    starts = outside_states(vf, 40, 0.1, seed=3, scene=scene)
    assert starts.shape == (40, 9)
    assert (values_at(vf, torch.as_tensor(starts, dtype=torch.float32), vf.system.horizon) > 0.1).all()
    fixed = np.array(scene.initial_state.state)
    jitter = np.broadcast_to(np.asarray(scene.initial_state.jitter, dtype=float), fixed.shape)
    assert (np.abs(starts - fixed) <= jitter + 1e-12).all()
    with pytest.raises(ValueError, match="starts of scene three-car-merge lie in"):
        outside_states(vf, 5, 50.0, seed=0, scene=scene, max_draws_per_episode=2)


@pytest.fixture
def make_pretrained(tmp_path, monkeypatch):
    """``benchmarks/make_pretrained.py`` as a module, writing the shipped Air3D files' copies in
    ``tmp_path`` (the package's own cards are left alone)."""
    import importlib.util
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "make_pretrained.py"
    spec = importlib.util.spec_from_file_location("make_pretrained", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    for f in pretrained.DIRECTORY.glob("air3d.*"):
        shutil.copy(f, tmp_path / f.name)
    monkeypatch.setattr(pretrained, "DIRECTORY", tmp_path)
    return module


def test_maintainers_record_another_evaluation_in_a_card(tmp_path, monkeypatch, make_pretrained) -> None:
    """``benchmarks/make_pretrained.py record`` files a ``reach evaluate`` run of the shipped file
    (here under the greedy policy) in the card's ``also_evaluated``: its source, policy, sample sizes
    and metrics from the run's JSON. Recording the same label again replaces it; a run that did not
    score the shipped model is refused by name."""
    import sys

    out = tmp_path / "greedy.csv"
    counts = ["--samples", "200", "--scenario-samples", "0", "--robust-samples", "0"]
    assert main(["evaluate", "pretrained:air3d", "--policy", "greedy", *counts, "--out", str(out)]) == 0
    results = json.loads(out.with_suffix(".json").read_text())
    record = ["make_pretrained.py", "record", "air3d", str(out.with_suffix(".json")), "--label", "greedy"]
    record += ["--command", "reach evaluate ...", "--commit", "abc", "--hardware", "test"]
    for _ in range(2):
        monkeypatch.setattr(sys, "argv", record)
        assert make_pretrained.main() == 0
    (entry,) = pretrained.card("air3d").also_evaluated
    row = results["results"][0]
    assert entry["policy"] == "greedy" and entry["source"] == "pretrained:air3d" and entry["samples"] == 200
    assert entry["metrics"]["collision_rate"] == row["collision_rate"]
    assert entry["metrics"]["false_safe_rate"] == row["false_safe_rate"]
    assert "greedy [pretrained:air3d, greedy policy], on 200 states" in pretrained.card("air3d").describe()
    results["results"][0]["source"] = "runs/another.pt"
    (tmp_path / "another.json").write_text(json.dumps(results))
    monkeypatch.setattr(sys, "argv", [*record[:3], str(tmp_path / "another.json"), *record[4:]])
    with pytest.raises(SystemExit, match=r"expected one scored row of pretrained:air3d .*found \[\]"):
        make_pretrained.main()
    # a device that does not exist here is refused by the parser, before any rollout, naming it
    monkeypatch.setattr(sys, "argv", ["make_pretrained.py", "evaluate", "air3d", "--device", "tpu"])
    with pytest.raises(SystemExit) as refused:
        make_pretrained.main()
    assert refused.value.code == 2


def test_maintainers_adopt_an_evaluation_of_the_same_network_scored_elsewhere(
    tmp_path, monkeypatch, make_pretrained
) -> None:
    """``benchmarks/make_pretrained.py adopt`` makes a ``reach evaluate`` run of the shipped network,
    scored from another file (a run directory on a GPU), the card's main evaluation: its sample sizes,
    the command given and the row's metrics. A checkpoint whose network differs from the shipped one
    by a single parameter, or a run under another policy than the cards' protocol, is refused, and
    the card is left as it was."""
    import sys

    import torch

    from training.checkpoint import network_from_payload, read_checkpoint, save_checkpoint

    run = tmp_path / "run"  # the same network in another file, as a run directory would hold it
    run.mkdir()
    shutil.copy(tmp_path / "air3d.pt", run / "checkpoint.pt")
    out = tmp_path / "elsewhere.csv"
    counts = ["--samples", "200", "--scenario-samples", "300", "--robust-samples", "0", "--seed", "3"]
    assert main(["evaluate", str(run / "checkpoint.pt"), *counts, "--out", str(out)]) == 0
    row = json.loads(out.with_suffix(".json").read_text())["results"][0]
    adopt = ["make_pretrained.py", "adopt", "air3d", str(out.with_suffix(".json"))]
    adopt += ["--command", "reach evaluate RUN ...", "--hardware", "test"]
    before = pretrained.card("air3d").evaluation
    payload = read_checkpoint(run / "checkpoint.pt")
    other = network_from_payload(run / "checkpoint.pt", payload)
    with torch.no_grad():
        next(other.parameters()).view(-1)[0] += 1e-6
    save_checkpoint(tmp_path / "other.pt", other, metadata={})
    monkeypatch.setattr(sys, "argv", [*adopt, "--checkpoint", str(tmp_path / "other.pt")])
    with pytest.raises(SystemExit, match=r"other.pt: its network is not the shipped air3d's"):
        make_pretrained.main()
    assert pretrained.card("air3d").evaluation == before
    greedy = json.loads(out.with_suffix(".json").read_text())
    greedy["settings"]["policy"] = "greedy"  # another policy's rollouts are not the card's protocol
    (tmp_path / "greedy.json").write_text(json.dumps(greedy))
    monkeypatch.setattr(sys, "argv", [*adopt[:3], str(tmp_path / "greedy.json"), *adopt[4:], "--checkpoint", str(run)])
    with pytest.raises(SystemExit, match=r"greedy.json: policy is 'greedy'; the cards' protocol has 'gradient'"):
        make_pretrained.main()
    assert pretrained.card("air3d").evaluation == before
    monkeypatch.setattr(sys, "argv", [*adopt, "--checkpoint", str(run)])
    assert make_pretrained.main() == 0
    evaluation = pretrained.card("air3d").evaluation
    assert (evaluation["samples"], evaluation["scenario_samples"], evaluation["seed"]) == (200, 300, 3)
    assert evaluation["command"] == "reach evaluate RUN ..." and evaluation["hardware"] == "test"
    assert evaluation["metrics"]["false_safe_rate"] == row["false_safe_rate"]
    assert evaluation["metrics"]["scenario_volume"] == row["scenario_volume"]


def test_every_card_carries_a_verdict_computed_from_its_figures():
    """The verdict is recomputed from the card's figures, never read: change a figure and it follows."""
    import dataclasses

    from training.pretrained.verdict import MAX_WRONG_CLAIMS, trust_verdict

    for c in pretrained.cards():
        verdict = c.verdict
        assert verdict.passes == (not verdict.failures), c.name
        assert verdict.line().startswith("passes" if verdict.passes else "fails (")
    air3d = pretrained.card("air3d")
    assert air3d.verdict.passes and "0.905 of the box" in air3d.verdict.scenario
    worse = dict(air3d.evaluation, metrics={**air3d.metrics, "false_safe_rate": 2 * MAX_WRONG_CLAIMS})
    failed = trust_verdict(dataclasses.replace(air3d, evaluation=worse), "avoid")
    assert not failed.passes and failed.failures == ("wrong claims 0.1 % > 0.05 %",)
    fewer = dict(air3d.evaluation, metrics={**air3d.metrics, "samples": 10_000})
    assert "10,000 states < 100,000" in trust_verdict(dataclasses.replace(air3d, evaluation=fewer), "avoid").failures
    no_set = dict(air3d.evaluation, metrics={**air3d.metrics, "scenario_volume": float("nan")})
    assert "no scenario set" in trust_verdict(dataclasses.replace(air3d, evaluation=no_set), "avoid").failures
    quad = pretrained.card("quadrotor").verdict
    assert not quad.passes and "wrong claims 4.54 % > 0.05 %" in quad.failures and "no scenario set" in quad.failures
    # the 9D filter's default is the capped model under the greedy input: that evaluation is judged
    assert "greedy policy" in pretrained.card("multivehicle9d").verdict.evaluation


def test_the_listings_show_each_models_verdict(capsys):
    from reach_cli import main

    assert main(["pretrained", "quadrotor", "air3d"]) == 0
    out = capsys.readouterr().out
    assert "trust bar: fails (wrong claims 4.54 % > 0.05 %" in out and "trust bar: passes" in out
    assert main(["envs"]) == 0
    out = capsys.readouterr().out
    assert "Quadrotor-v0" in out and "model=quadrotor (fails the trust bar)" in out
    assert "model=air3d (trusted)" in out and "yet" not in out


def test_every_wrapper_refuses_a_failing_default_and_reports_its_sources_verdict():
    """The Gymnasium, vector and PettingZoo wrappers take a shipped model only if its verdict passes,
    unless the user opts in by name; a value function the user passes is the user's choice, and each
    wrapper reports whether its source passed (None: the user's own, which has no card)."""
    import numpy as np

    from reach_envs.parallel import parallel_env
    from safety.filters.wrappers import SafetyFilterParallelWrapper, SafetyFilterVectorWrapper

    def vector():
        return gym.make_vec("MultiVehicle15D-v0", num_envs=2, vectorization_mode="vector_entry_point")

    makers = {
        "gymnasium": (lambda: gym.make("MultiVehicle15D-v0"), SafetyFilterWrapper),
        "vector": (vector, SafetyFilterVectorWrapper),
        "pettingzoo": (lambda: parallel_env("five-car-15d"), SafetyFilterParallelWrapper),
    }
    for label, (make, wrapper) in makers.items():
        with pytest.raises(ValueError, match=r"pretrained:multivehicle15d, the shipped model .* fails"):
            wrapper(make())
        opted = wrapper(make(), allow_untrusted=True)
        assert opted.source_trusted is False, label
        named = wrapper(make(), "pretrained:multivehicle15d")  # named by the user: their choice
        assert named.source_trusted is False, label
        with pytest.raises(ValueError, match="allow_untrusted must be True or False"):
            wrapper(make(), allow_untrusted="yes")
    env = SafetyFilterWrapper(gym.make("MultiVehicle15D-v0"), allow_untrusted=True)
    env.reset(seed=0)
    assert env.step(env.action_space.sample())[-1]["filter_source_trusted"] is False
    vec = SafetyFilterVectorWrapper(vector(), allow_untrusted=True)
    vec.reset(seed=0)
    assert vec.step(np.zeros(vec.action_space.shape))[-1]["filter_source_trusted"] is False
    trusted = SafetyFilterWrapper(gym.make("Air3D-v0"))
    assert trusted.source_trusted is True and trusted.source_verdict.passes
    own = SafetyFilterWrapper(gym.make("Air3D-v0"), load_value_function("pretrained:air3d").value_function)
    assert own.source_trusted is None  # a value function object: the user's own
