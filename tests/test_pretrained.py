"""The shipped value networks: each loads, fits its envs' physics, and reproduces its card's rates."""

from __future__ import annotations

import math
import shutil

import gymnasium as gym
import pytest

import reach_envs
from reach.cli import main
from safety.metrics import wilson_interval
from safety.value_functions import load_value_function
from safety.verify import VerifySettings, sample_states, verify
from safety.wrappers import SafetyFilterWrapper
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
        source = pretrained.for_env(env_id, system)
        assert env_id in pretrained.card(source[len(pretrained.PREFIX) :]).env_ids, (env_id, scene)


@pytest.mark.parametrize("name", NAMES)
def test_model_loads_and_fits_its_envs(name: str) -> None:
    card = pretrained.card(name)
    loaded = load_value_function(pretrained.PREFIX + name, system=card.system)
    assert loaded.label == pretrained.PREFIX + name and loaded.kind == "reach"
    assert loaded.layout == card.training["layout"]
    assert pretrained.checkpoint_path(name).stat().st_size < 1_000_000  # package data of a few hundred KB
    for env_id in card.env_ids:
        env = gym.make(env_id)
        assert env.unwrapped.system.same_physics(loaded.value_function.system), env_id
        filtered = SafetyFilterWrapper(env)  # no value function: the shipped one for this env
        filtered.reset(seed=0)
        _, _, _, _, info = filtered.step(filtered.action_space.sample())
        assert math.isfinite(info["filter_value"])
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
    settings = VerifySettings(samples=n, certify_samples=0, robust_samples=0, seed=card.evaluation["seed"] + 7919)
    row = verify(vf, sample_states(vf.system, n, settings.seed), settings, progress=False)
    for key in ("violation_rate", "false_safe_rate", "collision_rate"):
        low, high = wilson_interval(round(row[key] * n), n, z=Z)
        assert low <= metrics[key] <= high, f"{name}: {key} {row[key]:.4f} on {n} states, card {metrics[key]:.4f}"


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


def test_env_without_a_shipped_model_needs_a_value_function() -> None:
    env = reach_envs.make_env("relativepair", dt=0.02)
    if any(c.system == "relativepair" for c in pretrained.cards()):
        pytest.skip("a relativepair model ships")
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
    assert main(["evaluate", "pretrained:air3d", "--samples", "300", "--certify-samples", "0", "--out", str(out)]) == 0
    assert "pretrained:air3d" in out.read_text()


def test_starts_outside_the_learned_brt_come_from_the_scene() -> None:
    """--start-from scene keeps the scene's own starts (a merge stays a merge) that lie in {V > margin}."""
    import numpy as np
    import torch

    from reach_envs.scenes import make_scene
    from safety.filter_eval import outside_states
    from safety.verify import values_at

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
