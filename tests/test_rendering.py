"""Rendering and recording: frames, GIFs read back, the CLI's record command."""

from __future__ import annotations

import gymnasium as gym
import imageio.v2 as imageio
import numpy as np
import pytest

import reach_envs  # noqa: F401
from reach_cli import main
from reach_envs.recording import record_episode, save_gif


@pytest.mark.parametrize("env_id", ["Air3D-v0", "MultiVehicle9D-v0"])
def test_rgb_array_frames(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    for _ in range(10):
        env.step(env.action_space.sample())
    later = env.render()
    assert first.shape == later.shape == (400, 400, 3) and first.dtype == np.uint8
    assert first.std() > 5  # not a blank canvas
    assert not np.array_equal(first, later)  # cars moved and the clock advanced
    env.close()


def test_vector_env_renders_one_frame_per_env():
    venv = gym.make_vec("Air3D-v0", num_envs=2, vectorization_mode="vector_entry_point", render_mode="rgb_array")
    venv.reset(seed=0)
    frames = venv.render()
    assert len(frames) == 2 and frames[0].shape == (400, 400, 3) and not np.array_equal(frames[0], frames[1])


def test_record_episode_writes_a_gif_that_reads_back(tmp_path):
    env = gym.make("MultiVehicle9D-v0", scene="head-on", render_mode="rgb_array")
    summary = record_episode(env, tmp_path / "ep.gif", seed=0)
    frames = imageio.mimread(tmp_path / "ep.gif")
    assert len(frames) == summary["frames"] == summary["steps"] + 1
    assert np.asarray(frames[0]).shape[:2] == (400, 400)
    assert summary["collision"]  # the head-on scene collides when both cars go straight
    assert not list(tmp_path.glob(".ep-*"))  # no temp file left behind


def test_save_gif_rejects_bad_frames(tmp_path):
    with pytest.raises(ValueError, match="no frames"):
        save_gif([], tmp_path / "x.gif")
    with pytest.raises(ValueError, match="uint8"):
        save_gif([np.zeros((4, 4, 3), dtype=np.float32)], tmp_path / "x.gif")
    with pytest.raises(ValueError, match="render_mode"):
        record_episode(gym.make("Air3D-v0"), tmp_path / "x.gif")


def test_cli_envs_and_record(tmp_path, capsys):
    assert main(["envs"]) == 0
    listing = capsys.readouterr().out
    assert "Air3D-v0" in listing and "three-car-merge" in listing
    out = tmp_path / "a.gif"
    assert main(["record", "Air3D-v0", "--policy", "random", "--every", "5", "--out", str(out)]) == 0
    assert out.exists() and len(imageio.mimread(out)) >= 2
    assert main(["record", "Air3D-v0", "--scene", "nowhere", "--out", str(out)]) == 2
    assert "unknown scene" in capsys.readouterr().err
