"""The gallery of built-in systems (``docs/gallery.md``): one section per system, generated from it.

Each section gives the system's problem kind, state and input spaces, its dynamics and margins (its
own physics code run on symbols, :mod:`reach.systems.symbolic`), its Gymnasium id and PettingZoo
agents, a BRT slice where one is drawn (:func:`write_slices`, ``docs/gallery/NAME.png``), and the
metrics of its shipped model's card, or a line saying none ships yet. The docs build calls
:func:`gallery_markdown`; ``python benchmarks/gallery_slices.py`` redraws the slices.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

from reach.systems import make_system
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Ball

#: (registered name, where it comes from), in the gallery's order: DeepReach's public release first
GALLERY: tuple[tuple[str, str], ...] = (
    ("dubins3d", "DeepReach `Dubins3D` (reach mode; `set_mode='avoid'` for its avoid twin)"),
    ("parameterizedvertdrone2d", "DeepReach `ParameterizedVertDrone2D`"),
    ("multivehicle9d", "DeepReach `MultiVehicleCollision`"),
    ("narrowpassage", "DeepReach `NarrowPassage` (reach-avoid; `avoid_only=True` for its avoid variant)"),
    ("quadrotor", "DeepReach `Quadrotor` (avoid; `set_mode='reach'` for its reach variant)"),
    ("rocketlanding", "DeepReach `RocketLanding`: thrust in a disc of radius 250"),
    ("reachavoidrocketlanding", "DeepReach `ReachAvoidRocketLanding`: land past a wall, above the floor"),
    ("air3d", "the seed paper's pursuit-evasion game in relative coordinates"),
    ("relativepair", "the two-car problem whose pairwise union bounds the N-car family"),
    ("multivehicle6d", "Air3D in absolute coordinates"),
    ("multivehicle12d", "the N-car family: four cooperating cars"),
    ("multivehicle15d", "the N-car family: five cooperating cars"),
    ("dubinsreachavoid", "ours: a car reaching a goal past an obstacle in a wind"),
)

#: DeepReach systems not yet here, and why
MISSING: tuple[tuple[str, str], ...] = (("Dubins4D", "DeepReach's public release declares it without dynamics"),)

#: where the slices live, relative to the docs folder
SLICE_FOLDER = "gallery"


def _number(value: float) -> str:
    for k, text in ((1, "pi"), (2, "2 pi"), (0.5, "pi/2")):
        if math.isclose(abs(value), k * math.pi, rel_tol=1e-12):
            return f"-{text}" if value < 0 else text
    return f"{value:g}"


def _spaces(system: ControlAffineSystem) -> list[str]:
    rows = ["| state | range | periodic |", "|---|---|---|"]
    for name, (lo, hi), periodic in zip(system.state_names, system.domain, system.periodic, strict=True):
        rows.append(f"| `{name}` | [{_number(lo)}, {_number(hi)}] | {'yes' if periodic else ''} |")
    rows.append("")
    for what, box in (("control", system.control_bounds), ("disturbance", system.disturbance_bounds)):
        if box.dim:
            if isinstance(box, Ball):
                centre = ", ".join(_number(c) for c in box.center)
                rows.append(f"- {what} inputs ({box.dim}): the disc |u - ({centre})| <= {_number(box.radius)}")
                continue
            bounds = ", ".join(f"[{_number(lo)}, {_number(hi)}]" for lo, hi in zip(box.low, box.high))
            rows.append(f"- {what} inputs ({box.dim}): {bounds}")
        else:
            rows.append(f"- no {what} input")
    return rows


def _envs(name: str) -> list[str]:
    # lazy: the envs register with Gymnasium only when the gallery is drawn
    import reach_envs
    from reach_envs.agents import agent_inputs
    from reach_envs.scenes import SCENES

    ids = [i for i, f in reach_envs.SYSTEM_ENVS.items() if f.get("system") == name]
    scenes = {**reach_envs.ENV_SCENES, **{i: f["scene"] for i, f in reach_envs.SYSTEM_ENVS.items() if "scene" in f}}
    ids += [i for i, scene in scenes.items() if SCENES[scene]().system.name == name]
    agents = agent_inputs(make_system(name))
    lines = [f"- Gymnasium: {', '.join(f'`{i}`' for i in sorted(set(ids)))}" if ids else "- Gymnasium: "
             f'`gym.make("Reach-v0", system="{name}")`']  # fmt: skip
    if agents:
        lines.append(f"- PettingZoo agents: {', '.join(f'`{a}` (inputs {list(k)})' for a, k in agents.items())}")
    return lines


def _model(name: str) -> list[str]:
    from training import pretrained  # lazy: cards only when the gallery is drawn

    cards = [c for c in pretrained.cards() if c.system == name]
    if not cards:
        return ["- Shipped model: none yet."]
    lines = []
    for card in cards:
        m = card.metrics
        shown = ", ".join(
            f"{label} {m[key] * scale:.3g}"
            for key, label, scale in (
                ("violation_rate", "violation %", 100),
                ("false_safe_rate", "false safe %", 100),
                ("false_reachable_rate", "false reachable %", 100),
                ("scenario_volume", "scenario volume", 1),
                ("robust_scenario_volume", "robust volume", 1),
                ("iou_volume", "IoU vs grid", 1),
            )
            if isinstance(m.get(key), (int, float))
        )
        lines.append(
            f"- Shipped model `pretrained:{card.name}`: on {card.evaluation.get('samples', '?')} states, {shown} "
            "(statistical; [Pretrained models](pretrained.md) has the commands and every metric)."
        )
    return lines


def system_section(name: str, origin: str, docs_dir: str | os.PathLike | None = None) -> str:
    """The gallery's markdown section of the registered system ``name``."""
    # lazy: SymPy (through reach.systems.symbolic) only when equations are drawn
    from reach.systems.symbolic import equations

    system = make_system(name)
    eq = equations(system)
    margins = eq.margins_latex()
    title = {"failure": "failure margin l", "target": "target margin l", "constraint": "constraint margin g"}
    out = [
        f"## {type(system).__name__} (`{name}`)",
        "",
        f"{origin}. {'An' if system.kind == 'avoid' else 'A'} **{system.kind}** problem in {system.state_dim}D, "
        f"horizon {system.horizon:g}.",
        "",
        *_spaces(system),
        "",
        "\\[",
        eq.dynamics_latex(),
        "\\]",
        "",
        *(f"- {title[k]}: \\({v}\\)" for k, v in margins.items()),
        *_envs(name),
        *_model(name),
    ]
    if docs_dir is not None and (Path(docs_dir) / SLICE_FOLDER / f"{name}.png").is_file():
        out += ["", f"![{name}: BRT slice]({SLICE_FOLDER}/{name}.png)"]
    return "\n".join(out) + "\n"


def gallery_markdown(docs_dir: str | os.PathLike | None = None) -> str:
    """Every section of :data:`GALLERY`, then the DeepReach systems not yet here."""
    sections = [system_section(name, origin, docs_dir) for name, origin in GALLERY]
    missing = "\n".join(f"- **{what}**: {why}." for what, why in MISSING)
    return "\n".join(sections) + "\n## Not yet here\n\n" + missing + "\n"


def write_slices(folder: str | os.PathLike, names: Sequence[str] | None = None, grid: int = 51) -> list[Path]:
    """Draw ``folder/NAME.png``: the shipped model's zero level on the system's own slices, over a grid
    solution's BRT (filled) where the system has at most 3 dimensions (solved here on ``grid``^n
    nodes); systems with neither are skipped. Returns the files written."""
    # lazy: the solver, the models and matplotlib only when slices are drawn
    from groundtruth.solver import solve
    from safety.value_loading import load_value_function
    from studies.plots import plot_brt_slices
    from training import pretrained

    written = []
    for name in names if names is not None else [n for n, _ in GALLERY]:
        system = make_system(name)
        networks = [
            (f"pretrained:{c.name}", load_value_function(f"pretrained:{c.name}").value_function)
            for c in pretrained.cards()
            if c.system == name and c.format == "network"
        ]
        reference = None
        if system.state_dim <= 3:
            reference = solve(system, grid, [0.0, system.horizon], progress=False)
            reference.outside = "clamp"
        if not networks and reference is None:
            continue
        written.append(plot_brt_slices(networks, Path(folder) / f"{name}.png", reference=reference))
    return written


__all__ = ["GALLERY", "MISSING", "gallery_markdown", "system_section", "write_slices"]
