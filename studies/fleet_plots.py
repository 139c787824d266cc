"""Figures of the fleet study: collisions and goal rate against the fleet's size, and an episode's GIF."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from reach.atomic import atomic_path
from reach_envs.fleet import goal_seeking, rollout
from reach_envs.fleet_render import render_fleet
from reach_envs.fleet_scenes import FleetScene
from reach_envs.recording import save_gif
from studies.fleet_methods import make_method

__all__ = ["plot_fleet_eval", "record_fleet_gif"]


def plot_fleet_eval(rows: Sequence[dict[str, Any]], path: str | os.PathLike) -> Path:
    """Collision rate (with its 95 % interval) and goal rate against N, one column per scene and one
    line per method, to ``path`` (PNG, written atomically)."""
    import matplotlib  # lazy: matplotlib only when a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: as above

    layouts = list(dict.fromkeys(r["layout"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    fig, axes = plt.subplots(2, len(layouts), figsize=(4.2 * len(layouts), 6.4), squeeze=False, sharex=True)
    for c, layout in enumerate(layouts):
        for method in methods:
            mine = [r for r in rows if r["layout"] == layout and r["method"] == method]
            mine.sort(key=lambda r: r["n_cars"])
            if not mine:
                continue
            n = [r["n_cars"] for r in mine]
            rate = np.array([r["collision_rate"] for r in mine])
            low = np.maximum(rate - np.array([r["collision_low"] for r in mine]), 0.0)  # rounding: never < 0
            high = np.maximum(np.array([r["collision_high"] for r in mine]) - rate, 0.0)
            axes[0, c].errorbar(n, rate, yerr=[low, high], marker="o", capsize=3, label=method)
            axes[1, c].plot(n, [r["goal_rate"] for r in mine], marker="o", label=method)
        axes[0, c].set_title(layout)
        axes[1, c].set_xlabel("cars N")
        axes[1, c].set_xscale("log", base=2)
    axes[0, 0].set_ylabel("episodes with a collision")
    axes[1, 0].set_ylabel("share of cars at their goal")
    axes[0, -1].legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path


def record_fleet_gif(
    scene: FleetScene, method: str, path: str | os.PathLike, seed: int = 0, every: int = 2
) -> dict[str, Any]:
    """One episode of ``scene`` under ``method`` as a GIF at ``path`` (every ``every``-th step a
    frame); returns what happened: cars that collided, cars at their goal, steps."""
    decide = make_method(method, scene)

    def controller(x: torch.Tensor, goals: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        u = goal_seeking(x, goals, scene)
        return u if decide is None else decide(x, u, present)[0]

    x0, goals = scene.sample(1, np.random.default_rng(seed))
    outcome = rollout(scene, x0, goals, controller, record=True)
    assert outcome.states is not None and outcome.present is not None  # record=True keeps them
    picks = list(range(0, outcome.steps + 1, every))
    if picks[-1] != outcome.steps:
        picks.append(outcome.steps)
    frames = [render_fleet(outcome.states[k, 0], goals[0], outcome.present[k, 0], scene) for k in picks]
    save_gif(frames, path, fps=1.0 / (scene.dt * every))
    return {
        "collided": int(outcome.collided.sum()),
        "arrived": int(outcome.arrived.sum()),
        "steps": outcome.steps,
        "frames": len(frames),
    }
