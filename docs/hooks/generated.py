"""MkDocs hook: pages whose tables are generated from the code, so that they cannot drift from it.

``<!-- generated: environment table -->`` becomes one row per registered environment (spaces,
dynamics summary, horizon) built from its scene and system; ``<!-- generated: cli reference -->``
becomes every subcommand's ``--help``, defaults included (they come from the library's dataclasses);
``<!-- generated: pretrained cards -->`` becomes the shipped models' card table (package data, with
their measured scores and hardware: the results page); ``<!-- generated: pretrained list -->`` becomes
the list of shipped models, their systems and envs (the user page);
``<!-- generated: system gallery -->`` becomes one section per built-in system (:mod:`studies.gallery`).
"""

from __future__ import annotations

import io
from contextlib import redirect_stdout
from typing import Any


def _environment_table() -> str:
    import gymnasium as gym

    import reach_envs
    from reach_envs.scenes import SCENES

    rows = [
        "| id | scene | state (float32) | action in [-1, 1] | inputs (physical) | dt | horizon |",
        "|---|---|---|---|---|---:|---:|",
    ]
    for env_id, scene_name in reach_envs.ENV_SCENES.items():
        env = gym.make(env_id)
        scene = SCENES[scene_name]()
        system = scene.system
        state = ", ".join(system.state_names)
        control = ", ".join(
            f"[{lo:g}, {hi:g}]" for lo, hi in zip(system.control_bounds.low, system.control_bounds.high)
        )
        disturbance = scene.disturbance if isinstance(scene.disturbance, str) else "none"
        rows.append(
            f"| `{env_id}` | `{scene_name}` | `({state})` {env.observation_space.shape} | "
            f"`{env.action_space.shape}` | control {control}; disturbance: {disturbance} | {scene.dt:g} | "
            f"{scene.episode_horizon:g} s |"
        )
        env.close()
    named = ", ".join(f"`{name}`" for name in SCENES)
    return "\n".join(rows) + f"\n\nNamed scenes: {named}.\n"


def _cli_reference() -> str:
    from reach_cli import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    out = []
    for module in COMMANDS:
        name = module.__name__.rsplit(".", 1)[1].replace("_", "-")
        buf = io.StringIO()
        with redirect_stdout(buf):
            sub.choices[name].print_help()
        out.append(f"## `reach {name}`\n\n```text\n{buf.getvalue().rstrip()}\n```\n")
    return "\n".join(out)


def _pretrained_cards() -> str:
    from training import pretrained

    rows = [
        "| model | system, envs | trained | violation % | false safe (reach) % | collision % | scenario vol. | "
        "robust vol. (eps) | misses union % | IoU vol. |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    commands = []
    for card in pretrained.cards():
        t = card.training
        if card.format == "grid":
            trained = "solved, " + "x".join(str(n) for n in t.get("grid", ())) + " grid"
        else:
            trained = f"{t.get('steps')} steps, {t.get('wall_time_s', 0) / 60:.0f} min"
        rows.append(_card_row(f"`pretrained:{card.name}`", f"{card.system}; {', '.join(card.env_ids) or '-'}", trained,
                              card.metrics))  # fmt: skip
        for other in card.also_evaluated:
            what = f"`{other.get('source')}`, {other.get('policy', 'gradient')} policy"
            rows.append(_card_row(f"&nbsp;&nbsp;{other.get('label')}", what, "the same file", other.get("metrics", {})))
        extra = "".join(
            f"\n\nAlso {other.get('label')} ({other.get('samples', '?')} states, commit {other.get('commit', '?')}; "
            f"{other.get('hardware', '?')}):\n\n```bash\n{other.get('command', '')}\n```"
            for other in card.also_evaluated
        )
        commands.append(
            f"**`{card.name}`**: {card.summary}\n\n```bash\n{t.get('command', '')}\n"
            f"{card.evaluation.get('command', '')}\n```\n\nHardware: {t.get('hardware', '?')}; "
            f"commit {t.get('commit', '?')}; evaluated on {card.evaluation.get('samples', '?')} states.{extra}"
        )
    return "\n".join(rows) + "\n\n" + "\n\n".join(commands) + "\n"


def _pretrained_list() -> str:
    from training import pretrained

    rows = ["| source | kind | system | Gymnasium envs |", "|---|---|---|---|"]
    for card in pretrained.cards():
        kind = "grid" if card.format == "grid" else "value network"
        envs = ", ".join(f"`{env_id}`" for env_id in card.env_ids) or "-"
        rows.append(f"| `pretrained:{card.name}` | {kind} | `{card.system}` | {envs} |")
    return "\n".join(rows) + "\n"


def _card_row(model: str, what: str, trained: str, m: dict) -> str:
    """One row of the cards' table: a card's evaluation or one of its other evaluations."""

    def cell(key: str, scale: float = 1.0) -> str:
        value = m.get(key)
        return f"{value * scale:.3g}" if isinstance(value, (int, float)) else "-"

    # an avoid row's false safe, a reach or reach-avoid row's false reachable: the same error, a wrong claim
    false_claim = cell("false_safe_rate", 100) if "false_safe_rate" in m else cell("false_reachable_rate", 100)
    volume, eps = m.get("robust_scenario_volume"), m.get("robust_eps")
    robust = f"{volume:.3g} ({eps:.2g})" if isinstance(volume, (int, float)) and isinstance(eps, (int, float)) else "-"
    return (
        f"| {model} | {what} | {trained} | {cell('violation_rate', 100)} | {false_claim} | "
        f"{cell('collision_rate', 100)} | {cell('scenario_volume')} | {robust} | "
        f"{cell('containment_miss_rate', 100)} | {cell('iou_volume')} |"
    )


def _system_gallery() -> str:
    from pathlib import Path

    from studies.gallery import gallery_markdown

    return gallery_markdown(Path(__file__).resolve().parents[1])


GENERATORS = {
    "<!-- generated: environment table -->": _environment_table,
    "<!-- generated: cli reference -->": _cli_reference,
    "<!-- generated: pretrained cards -->": _pretrained_cards,
    "<!-- generated: pretrained list -->": _pretrained_list,
    "<!-- generated: system gallery -->": _system_gallery,
}


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    for marker, make in GENERATORS.items():
        if marker in markdown:
            markdown = markdown.replace(marker, make())
    return markdown
