"""Figures of learned value functions: BRT slices against ground truth, violation bars, episode GIFs.

All figures use Matplotlib's object API with the Agg canvas (no display needed) and are written
atomically as PNG.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from reach.atomic import atomic_path
from reach.systems import ControlAffineSystem
from reach.systems.multivehicle import DEEPREACH_9D_SLICE
from reach.value_function import ValueFunction


@dataclass(frozen=True)
class SliceSpec:
    """A 2D slice: a base state, the two dimensions that vary over the domain, a title."""

    base: tuple[float, ...]
    axes: tuple[int, int] = (0, 1)
    title: str = ""


def default_slices(system: ControlAffineSystem) -> list[SliceSpec]:
    """The system's own plot slices (:meth:`~reach.systems.base.ControlAffineSystem.plot_slices`):
    Air3D's reference slice and two more, DeepReach's 9D slices, and for any other system the domain
    centre over its view dimensions."""
    return [SliceSpec(tuple(base), tuple(axes), title) for base, axes, title in system.plot_slices()]


def slice_states(
    system: ControlAffineSystem, spec: SliceSpec, resolution: int
) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    """Axis values of the two varying dimensions and the ``(resolution^2, n)`` states of the slice."""
    if len(spec.base) != system.state_dim:
        raise ValueError(f"slice base state has {len(spec.base)} entries, {system.name} has {system.state_dim}")
    i, j = spec.axes
    a = np.linspace(*system.domain[i], resolution)
    b = np.linspace(*system.domain[j], resolution)
    x = torch.tensor(spec.base, dtype=torch.float32).repeat(resolution * resolution, 1)
    ga, gb = np.meshgrid(a, b, indexing="ij")
    x[:, i] = torch.as_tensor(ga.ravel(), dtype=torch.float32)
    x[:, j] = torch.as_tensor(gb.ravel(), dtype=torch.float32)
    return a, b, x


def plot_brt_slices(
    value_functions: Sequence[tuple[str, ValueFunction]],
    path: str | os.PathLike,
    t: float | None = None,
    slices: Sequence[SliceSpec] | None = None,
    reference: ValueFunction | None = None,
    resolution: int = 161,
    level: float = 0.0,
) -> Path:
    """Zero-level contours ``{V = level}`` of each value function on each slice, the reference BRT filled."""
    # lazy: matplotlib only when drawing
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not value_functions and reference is None:
        raise ValueError("nothing to plot: give at least one value function or a reference")
    system = (value_functions[0][1] if value_functions else reference).system
    t = system.horizon if t is None else float(t)
    slices = list(slices) if slices is not None else default_slices(system)
    names = system.state_names
    fig = Figure(figsize=(4.2 * len(slices), 4.2), dpi=100)
    FigureCanvasAgg(fig)
    colours = [f"C{k}" for k in range(10)]
    for s, spec in enumerate(slices):
        ax = fig.add_subplot(1, len(slices), s + 1)
        a, b, x = slice_states(system, spec, resolution)
        if reference is not None:
            ref = reference.value(x, t).reshape(resolution, resolution).numpy()
            ax.contourf(a, b, ref.T, levels=[-1e9, level], colors=["0.8"])
            ax.contour(a, b, ref.T, levels=[level], colors="k", linewidths=2.0)
        for k, (label, vf) in enumerate(value_functions):
            v = vf.value(x, t).detach().reshape(resolution, resolution).cpu().numpy()
            if v.min() <= level <= v.max():
                ax.contour(a, b, v.T, levels=[level], colors=colours[k % 10], linewidths=1.3)
            ax.plot([], [], color=colours[k % 10], label=label)
        if reference is not None:
            ax.plot([], [], color="k", lw=2, label="ground truth (grey: BRT)")
        ax.set_xlabel(names[spec.axes[0]])
        ax.set_ylabel(names[spec.axes[1]])
        ax.set_aspect("equal")
        ax.set_title(f"{spec.title}, t = {t:g}", fontsize=9)
        if s == 0:
            ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def plot_violation_bars(rows: Sequence[dict[str, Any]], path: str | os.PathLike) -> Path:
    """Stacked bars per value function: false-safe and false-unsafe violation rates, collision rate beside."""
    # lazy: matplotlib only when drawing
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = [r for r in rows if not r.get("error")]
    if not rows:
        raise ValueError("no evaluated rows to plot")
    labels = [f"{r['label']}\n({r.get('layout', '')})" for r in rows]
    xs = np.arange(len(rows))
    fs = np.array([100 * r["false_safe_rate"] for r in rows])
    fu = np.array([100 * r["false_unsafe_rate"] for r in rows])
    col = np.array([100 * r["collision_rate"] for r in rows])
    fig = Figure(figsize=(max(5.0, 1.1 * len(rows) + 2), 4.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.bar(xs - 0.2, fs, 0.4, label="false safe (V > 0, collides)", color="C3")
    ax.bar(xs - 0.2, fu, 0.4, bottom=fs, label="false unsafe (V <= 0, safe)", color="C1")
    ax.bar(xs + 0.2, col, 0.4, label="collision rate", color="C0")
    ax.set_xticks(xs, labels, fontsize=8)
    ax.set_ylabel("% of sampled states")
    ax.set_ylim(0, 1.3 * max(float(col.max()), float((fs + fu).max()), 1e-3))
    ax.legend(fontsize=8, loc="upper left", ncol=2)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def record_filtered_episode(
    value_function: ValueFunction | str,
    path: str | os.PathLike,
    scene: Any = None,
    threshold: float | None = None,
    seed: int = 0,
    adversary: bool = True,
    every: int = 1,
) -> dict[str, Any]:
    """A GIF of one safety-filtered episode whose nominal policy drives straight.

    ``scene`` is a named scene or a :class:`~reach_envs.scenes.Scene`; by default ``air3d`` for an
    Air3D value function and a plain scene of the value function's system otherwise.

    With ``adversary=True`` and a system with a disturbance, the pursuer plays the value function's
    worst-case ``d*`` (at the system's horizon), which is what the filter is built to withstand.
    """
    import gymnasium as gym  # lazy: gymnasium only for episode GIFs

    # lazy: the envs and the filter stack only for episode GIFs
    from reach_envs.env import ReachEnv
    from reach_envs.recording import record_episode
    from reach_envs.scenes import system_scene
    from safety.filters.settings import FilterSettings
    from safety.filters.wrappers import SafetyFilterWrapper
    from safety.value_loading import as_value_function
    from safety.value_policies import worst_case_disturbance

    vf = as_value_function(value_function)
    if scene is None:
        scene = "air3d" if vf.system.name == "air3d" else system_scene(vf.system)
    overrides: dict[str, Any] = {"trails": True}
    if adversary and vf.system.disturbance_dim:
        overrides["disturbance"] = worst_case_disturbance(vf)
    settings = FilterSettings(threshold=threshold)  # the other filter options at their defaults
    env: gym.Env = SafetyFilterWrapper(ReachEnv(scene, render_mode="rgb_array", **overrides), vf, settings=settings)
    summary = record_episode(env, path, seed=seed, every=every)
    env.close()
    return summary


def parse_slice(text: str, system: ControlAffineSystem) -> SliceSpec:
    """A slice from ``"x2=-0.4,y2=0,...;x1,y1"``: fixed values by state name, then the two axes.

    Unnamed dimensions sit at the centre of their domain (the DeepReach slice's defaults for 9D).
    """
    names = list(system.state_names)
    try:
        fixed, axes = text.split(";")
    except ValueError:
        raise ValueError(f"slice {text!r} must look like 'name=value,...;axis1,axis2'") from None
    base = list(DEEPREACH_9D_SLICE) if len(names) == 9 else [0.5 * (a + b) for a, b in system.domain]
    for item in filter(None, (s.strip() for s in fixed.split(","))):
        key, _, value = item.partition("=")
        if key not in names:
            raise ValueError(f"slice: unknown state name {key!r}; names are {names}")
        base[names.index(key)] = float(eval_number(value))
    axis_names = [a.strip() for a in axes.split(",")]
    if len(axis_names) != 2 or any(a not in names for a in axis_names):
        raise ValueError(f"slice: give two axes among {names}, got {axes!r}")
    return SliceSpec(tuple(base), (names.index(axis_names[0]), names.index(axis_names[1])), fixed)


def eval_number(text: str) -> float:
    """A float, allowing ``pi`` multiples such as ``3pi/4``, ``-pi/2`` or ``0.5pi``."""
    t = text.strip().replace(" ", "")
    if "pi" not in t:
        return float(t)
    head, _, tail = t.partition("pi")
    factor = -1.0 if head == "-" else (1.0 if head in ("", "+") else float(head))
    divisor = float(tail[1:]) if tail.startswith("/") else 1.0
    if tail and not tail.startswith("/"):
        raise ValueError(f"cannot read {text!r} as a number")
    return factor * math.pi / divisor


def plot_union_overlay(
    value_functions: Sequence[tuple[str, ValueFunction]],
    union: ValueFunction,
    path: str | os.PathLike,
    slices: Sequence[SliceSpec] | None = None,
    t: float | None = None,
    resolution: int = 161,
) -> Path:
    """One panel per (model, slice): the learned BRT, the union of pairwise BRTs, and where the
    union is *not* inside the learned BRT (provably wrong there), in distinct colours."""
    # lazy: matplotlib only when drawing
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    if not value_functions:
        raise ValueError("give at least one value function to overlay on the union")
    system = union.system
    t = system.horizon if t is None else float(t)
    slices = list(slices) if slices is not None else default_slices(system)
    rows, cols = len(slices), len(value_functions)
    fig = Figure(figsize=(max(7.5, 3.8 * cols), 3.8 * rows + 0.6), dpi=100)
    FigureCanvasAgg(fig)
    # 0 outside both, 1 learned only, 2 both, 3 union only (missed)
    cmap = ListedColormap(["white", "#9ecae1", "#756bb1", "#de2d26"])
    for c, (label, vf) in enumerate(value_functions):
        for r, spec in enumerate(slices):
            ax = fig.add_subplot(rows, cols, r * cols + c + 1)
            a, b, x = slice_states(system, spec, resolution)
            learned = (vf.value(x, t).detach().cpu() <= 0).reshape(resolution, resolution).numpy()
            inside_union = (union.value(x, t) <= 0).reshape(resolution, resolution).numpy()
            code = np.where(inside_union, np.where(learned, 2, 3), np.where(learned, 1, 0))
            ax.pcolormesh(a, b, code.T, cmap=cmap, vmin=-0.5, vmax=3.5, shading="auto")
            missed = float((inside_union & ~learned).sum()) / max(1, int(inside_union.sum()))
            ax.set_title(f"{label}: misses {100 * missed:.1f} % of union\n{spec.title}", fontsize=7)
            ax.set_xlabel(system.state_names[spec.axes[0]])
            ax.set_ylabel(system.state_names[spec.axes[1]])
            ax.set_aspect("equal")
    handles = [
        Patch(color="#9ecae1", label="learned BRT only"),
        Patch(color="#756bb1", label="learned BRT and union"),
        Patch(color="#de2d26", label="union only (learned model wrong)"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def plot_filter_tradeoff(rows: Sequence[dict[str, Any]], path: str | os.PathLike, title: str = "") -> Path:
    """Collision rate (with its interval) against goal-reaching rate; one curve per value function
    across thresholds, the nominal policy as a single point."""
    # lazy: matplotlib only when drawing
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not rows:
        raise ValueError("no filter-evaluation rows to plot")
    fig = Figure(figsize=(5.6, 4.2), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(r.get("value_function", r["label"]) if r["filtered"] else "nominal", []).append(r)
    for k, (name, rs) in enumerate(groups.items()):
        rs = sorted(rs, key=lambda r: r["threshold"] if r["threshold"] is not None else -1)
        x = [r["goal_rate"] for r in rs]
        y = [100 * r["collision_rate"] for r in rs]
        err = [
            [max(0.0, 100 * (r["collision_rate"] - r["collision_ci_low"])) for r in rs],
            [max(0.0, 100 * (r["collision_ci_high"] - r["collision_rate"])) for r in rs],
        ]
        style = "s" if name == "nominal" else "o-"
        ax.errorbar(x, y, yerr=err, fmt=style, color="k" if name == "nominal" else f"C{k}", capsize=3, label=name)
        for r, xi, yi in zip(rs, x, y):
            if r["threshold"] is not None:
                ax.annotate(f"{r['threshold']:g}", (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_xlabel("goal-reaching rate")
    ax.set_ylabel("collision rate (%)")
    ax.set_title(title or "safety against task performance (labels: thresholds)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)
