"""Episode recording to GIF with imageio; files are written atomically (temp file, then rename)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from reach.atomic import atomic_path
from reach.validation import check_int


def save_gif(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 25.0) -> Path:
    """Write RGB uint8 frames ``(H, W, 3)`` to a looping GIF at ``path`` atomically."""
    import imageio.v2 as imageio  # lazy: imageio only when writing a GIF

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


Policy = Callable[[np.ndarray], Any]


@dataclass(frozen=True)
class RecordingSettings:
    """How much of the episodes a recording keeps: ``max_steps`` per episode (None: until every
    panel has ended) and every ``every``-th frame (the GIF then plays at the env's ``render_fps``
    divided by ``every``, so it lasts as long as the episode). Checked when made."""

    max_steps: int | None = None
    every: int = 1

    def __post_init__(self) -> None:
        if self.max_steps is not None:
            object.__setattr__(self, "max_steps", check_int("max_steps", self.max_steps, 0))
        object.__setattr__(self, "every", check_int("every", self.every, 1))


def record_episode(
    env: gym.Env,
    path: str | os.PathLike,
    policy: Policy | None = None,
    seed: int | None = None,
    max_steps: int | None = None,
    every: int = 1,
) -> dict[str, Any]:
    """Run one episode of an ``rgb_array`` env and save it as a GIF.

    ``policy(obs) -> action`` drives the agent (default: zero action, i.e. go straight). Every
    ``every``-th frame is kept. Returns a summary: path, steps, whether it collided, total reward.
    """
    return record_panels([env], path, [policy], [seed], settings=RecordingSettings(max_steps, every))


def record_panels(
    envs: Sequence[gym.Env],
    path: str | os.PathLike,
    policies: Sequence[Policy | None],
    seeds: Sequence[int | None],
    options: Sequence[dict[str, Any] | None] | None = None,
    settings: RecordingSettings | None = None,
    caption: Callable[[int, dict[str, Any] | None], str] | None = None,
    on_reset: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """The one episode recorder: episodes of several envs side by side, in lockstep, into one GIF.

    For each seed in ``seeds`` (episode ``k``), every env is reset with that seed (and
    ``options[k]``), ``on_reset(k)`` is called (to reset a task), and the envs are stepped together
    with their ``policies`` (None: zero action) until all have ended or ``settings.max_steps``
    steps have run (:class:`RecordingSettings`, default: no limit, every frame); an env that ended
    shows its last frame. ``caption(j, info)``, if given, writes a header over panel ``j`` from its
    last step info. Returns the path, steps (of the longest panel, summed over episodes), whether
    any panel collided, the first panel's total reward, and the frame count.
    """
    if any(env.render_mode != "rgb_array" for env in envs):
        raise ValueError("recording needs envs made with render_mode='rgb_array'")
    if settings is None:
        settings = RecordingSettings()
    max_steps, every = settings.max_steps, settings.every
    frames: list[np.ndarray] = []
    steps, total, collided = 0, 0.0, False
    for k, seed in enumerate(seeds):
        obs = [env.reset(seed=seed, options=None if options is None else options[k])[0] for env in envs]
        if on_reset is not None:
            on_reset(k)
        done = [False] * len(envs)
        infos: list[dict[str, Any] | None] = [None] * len(envs)
        last = [env.render() for env in envs]
        frames.append(_join(last, infos, caption))
        n = 0
        while not all(done) and (max_steps is None or n < max_steps):
            for j, env in enumerate(envs):
                if done[j]:
                    continue
                policy = policies[j]
                action = np.zeros(env.action_space.shape, env.action_space.dtype) if policy is None else policy(obs[j])
                obs[j], reward, terminated, truncated, infos[j] = env.step(action)
                total += float(reward) if j == 0 else 0.0
                collided = collided or bool(infos[j].get("collision", False))
                done[j] = terminated or truncated
                last[j] = env.render()
            n += 1
            if n % every == 0 or all(done):
                frames.append(_join(last, infos, caption))
        steps += n
    fps = envs[0].metadata.get("render_fps", 25) / every
    out = save_gif(frames, path, fps=fps)
    return {"path": str(out), "steps": steps, "collision": collided, "return": total, "frames": len(frames)}


def _join(
    pictures: Sequence[np.ndarray],
    infos: Sequence[dict[str, Any] | None],
    caption: Callable[[int, dict[str, Any] | None], str] | None,
) -> np.ndarray:
    """Panels side by side, each under its caption strip when ``caption`` is given."""
    if caption is not None:
        pictures = [_captioned(p, caption(j, infos[j])) for j, p in enumerate(pictures)]
    return np.concatenate([p[..., :3] for p in pictures], axis=1) if len(pictures) > 1 else pictures[0][..., :3]


def _captioned(frame: np.ndarray, text: str) -> np.ndarray:
    """``frame`` with a header strip carrying ``text`` (red when it says the filter is active)."""
    from PIL import Image, ImageDraw  # lazy: PIL only when drawing captions

    strip = Image.new("RGB", (frame.shape[1], 22), "white")
    ImageDraw.Draw(strip).text((8, 5), text, fill=(200, 0, 0) if "ACTIVE" in text else (0, 0, 0))
    return np.concatenate([np.asarray(strip), frame[..., :3]], axis=0)
