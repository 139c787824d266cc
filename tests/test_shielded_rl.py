"""Shielded reinforcement learning (docs/shielded_rl.md, benchmarks/shielded_rl.py): a PPO agent
trained through the safety filter collides in none of its training episodes, the filter really acts
(the env simulates the filtered action, not the agent's), and the page's example and command run
and parse as written. Skipped without the ``rl`` extra (stable-baselines3)."""

from __future__ import annotations

import math
import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import torch

from safety import load_value_function

pytest.importorskip("stable_baselines3")

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "shielded_rl.md"


@pytest.fixture(scope="module")
def study(request: pytest.FixtureRequest):
    """The benchmark script as a module (benchmarks/ is no package)."""
    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    request.addfinalizer(monkeypatch.undo)
    import shielded_rl

    return shielded_rl


@pytest.fixture(scope="module")
def vf():
    return load_value_function("pretrained:air3d").value_function


def test_the_env_simulates_the_filtered_action(study, vf):
    """An agent that turns toward the pursuer, from the same 20 starts and goals: unfiltered, most
    episodes collide; filtered, none does, and every step the env turned at the rate the filter
    applied (3 rad/s per unit of action), which on its interventions is not the agent's."""
    starts = study.start_pool(vf, 256, 0.1, seed=3)
    collided = {}
    for shielded in (False, True):
        env, log = study.make_env(starts, vf if shielded else None)
        replaced = 0
        for k in range(20):
            obs, _ = env.reset(seed=k)
            done = False
            while not done:
                ram = np.array([np.clip(math.atan2(obs[1], obs[0]), -1.0, 1.0)], np.float32)  # the pursuer's bearing
                obs, _, terminated, truncated, info = env.step(ram)
                done = terminated or truncated
                if shielded:
                    assert info["nominal_action"][0] == ram[0]
                    assert info["control"][0] == pytest.approx(3.0 * info["applied_action"][0])
                    replaced += bool(info["filter_intervened"] and info["applied_action"][0] != ram[0])
        collided[shielded] = log.collisions
        assert log.episodes == 20
    assert collided[False] >= 5, "few unfiltered episodes collide: the check below would prove little"
    assert collided[True] == 0
    assert replaced > 20


def test_shielded_ppo_trains_without_collisions(study, vf):
    """A few hundred PPO steps per arm, same seed, same starts: the shielded agent's training episodes
    never collide while the filter intervenes; the unshielded agent's are counted the same way."""
    plain = study.train_arm("unshielded", 0, 512, vf)
    shielded = study.train_arm("shielded", 0, 512, vf)
    assert plain.train_episodes > 5 and shielded.train_episodes > 5
    assert shielded.train_collisions == 0
    assert shielded.train_intervention_rate > 0.01
    assert plain.train_intervention_rate is None
    assert np.isfinite(shielded.train_mean_return)
    table = study.tables(study.Study(results=[plain, shielded]))
    assert "| **shielded, all seeds** | - |" in table and f"| {shielded.train_episodes} | 0 (0.0 %) |" in table


def test_the_page_command_parses_and_its_example_runs(study, tmp_path, monkeypatch):
    """The page's study command is one the script accepts, and its first Python block runs."""
    text = PAGE.read_text()
    commands = re.findall(r"^python benchmarks/shielded_rl\.py.*$", text, re.M)
    assert commands, "docs/shielded_rl.md shows no command of benchmarks/shielded_rl.py"
    monkeypatch.chdir(tmp_path)  # where a command's --out would write
    calls = []
    monkeypatch.setattr(study, "run_study", lambda *a, **k: calls.append((a, k)) or study.Study())
    threads = torch.get_num_threads()
    try:
        for command in commands:
            assert study.main(shlex.split(command)[2:]) == 0
    finally:
        torch.set_num_threads(threads)  # main() sets its own count; later tests keep theirs
    assert len(calls) == len(commands)
    block = re.search(r"```python\n(.*?)```", text, re.S)
    assert block, "docs/shielded_rl.md has no Python example"
    exec(compile(block.group(1), "docs/shielded_rl.md (Python block 1)", "exec"), {"__name__": "docs_example"})
