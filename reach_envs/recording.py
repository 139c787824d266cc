"""Episode recording to GIF with imageio; files are written atomically (temp file, then rename)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from reach.atomic import atomic_path


def save_gif(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 25.0) -> Path:
    """Write RGB uint8 frames ``(H, W, 3)`` to a looping GIF at ``path`` atomically."""
    import imageio.v2 as imageio

    if len(frames) == 0:
        raise ValueError("save_gif: no frames to write")
    for k, f in enumerate(frames):
        if f.ndim != 3 or f.shape[2] != 3 or f.dtype != np.uint8:
            raise ValueError(f"save_gif: frame {k} must be uint8 (H, W, 3), got {f.dtype} {f.shape}")
    if not (fps > 0 and np.isfinite(fps)):
        raise ValueError(f"save_gif: fps must be positive, got {fps}")
    with atomic_path(path) as tmp:
        imageio.mimsave(tmp, list(frames), format="GIF", duration=1000.0 / fps, loop=0)
    return Path(path)


def record_episode(
    env: gym.Env,
    path: str | os.PathLike,
    policy: Callable[[np.ndarray], Any] | None = None,
    seed: int | None = None,
    max_steps: int | None = None,
    every: int = 1,
) -> dict[str, Any]:
    """Run one episode of an ``rgb_array`` env and save it as a GIF.

    ``policy(obs) -> action`` drives the agent (default: zero action, i.e. go straight). Every
    ``every``-th frame is kept. Returns a summary: path, steps, whether it collided, total reward.
    """
    if env.render_mode != "rgb_array":
        raise ValueError(f"record_episode needs an env made with render_mode='rgb_array', got {env.render_mode!r}")
    obs, info = env.reset(seed=seed)
    frames = [env.render()]
    zero = np.zeros(env.action_space.shape, dtype=env.action_space.dtype)
    steps, total, collided = 0, 0.0, False
    while max_steps is None or steps < max_steps:
        action = zero if policy is None else policy(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        steps += 1
        total += float(reward)
        collided = collided or bool(info.get("collision", False))
        if steps % every == 0 or terminated or truncated:
            frames.append(env.render())
        if terminated or truncated:
            break
    fps = env.metadata.get("render_fps", 25) / every
    out = save_gif(frames, path, fps=fps)
    return {"path": str(out), "steps": steps, "collision": collided, "return": total, "frames": len(frames)}
