"""MkDocs hook: pages whose tables are generated from the code, so that they cannot drift from it.

``<!-- generated: environment table -->`` becomes one row per registered environment (spaces,
dynamics summary, horizon) built from its scene and system; ``<!-- generated: cli reference -->``
becomes every subcommand's ``--help``, defaults included (they come from the library's dataclasses);
``<!-- generated: pretrained cards -->`` becomes the shipped models' card table (package data).
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
    from reach.cli import COMMANDS, build_parser

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

    def robust(m: dict) -> str:
        volume, eps = m.get("robust_certified_volume"), m.get("robust_eps")
        known = isinstance(volume, (int, float)) and isinstance(eps, (int, float))
        return f"{volume:.3g} ({eps:.2g})" if known else "-"

    rows = [
        "| model | system, envs | trained | violation % | false safe % | collision % | certified vol. | "
        "robust vol. (eps) | misses union % | IoU vol. |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    commands = []
    for card in pretrained.cards():
        t, m = card.training, card.metrics

        def cell(key: str, scale: float = 1.0, m: dict = m) -> str:
            value = m.get(key)
            return f"{value * scale:.3g}" if isinstance(value, (int, float)) else "-"

        rows.append(
            f"| `pretrained:{card.name}` | {card.system}; {', '.join(card.env_ids) or '-'} | "
            f"{t.get('steps')} steps, {t.get('wall_time_s', 0) / 60:.0f} min | {cell('violation_rate', 100)} | "
            f"{cell('false_safe_rate', 100)} | {cell('collision_rate', 100)} | {cell('certified_volume')} | "
            f"{robust(m)} | {cell('containment_miss_rate', 100)} | {cell('iou_volume')} |"
        )
        commands.append(
            f"**`{card.name}`**: {card.summary}\n\n```bash\n{t.get('command', '')}\n"
            f"{card.evaluation.get('command', '')}\n```\n\nHardware: {t.get('hardware', '?')}; "
            f"commit {t.get('commit', '?')}; evaluated on {card.evaluation.get('samples', '?')} states."
        )
    return "\n".join(rows) + "\n\n" + "\n\n".join(commands) + "\n"


GENERATORS = {
    "<!-- generated: environment table -->": _environment_table,
    "<!-- generated: cli reference -->": _cli_reference,
    "<!-- generated: pretrained cards -->": _pretrained_cards,
}


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    for marker, make in GENERATORS.items():
        if marker in markdown:
            markdown = markdown.replace(marker, make())
    return markdown
