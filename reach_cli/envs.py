"""``reach envs``: the registered environments, the named scenes and the PettingZoo (multi-agent) envs."""

from __future__ import annotations

import argparse
from typing import Any

from reach_cli.options import add_subparser
from training import pretrained


def add_parser(sub: Any) -> None:
    p = add_subparser(sub, "envs", help="list the registered environments and named scenes")
    p.set_defaults(func=run)


def _agents(agents: dict[str, tuple[int, ...]] | None) -> str:
    return str(len(agents)) if agents else "-"


def _model(env_id: str, scene: Any) -> str:
    """The shipped model a filter on ``env_id`` uses by default, and whether it passes the trust bar."""
    found = pretrained.card_for_env(env_id, scene.system)
    if found is None:
        return "model=- (give a value function)"
    return f"model={found.name} ({'trusted' if found.verdict.passes else 'fails the trust bar'})"


def _line(env_id: str, source: str, scene: Any, agents: dict[str, tuple[int, ...]] | None) -> str:
    """One environment: its scene or system, the system's kind and sizes, disturbance, step and horizon,
    and the shipped model its filter uses by default with that model's verdict."""
    s = scene.system
    d = scene.disturbance
    disturbance = "none" if d is None else (d if isinstance(d, str) else "custom")
    state = f"{s.state_dim}D"
    return (
        f"  {env_id:<28} {source:<31} kind={s.kind:<12} state={state:<4} action={s.control_dim} "
        f"agents={_agents(agents)} disturbance={disturbance} dt={scene.dt:g} horizon={scene.episode_horizon:g} "
        f"{_model(env_id, scene)}"
    )


def run(args: argparse.Namespace) -> int:
    # lazy: gymnasium and the envs only when this command runs
    import reach_envs
    from reach_envs.agents import agent_inputs
    from reach_envs.fleet_scenes import MAX_CARS
    from reach_envs.scenes import SCENES, env_scene

    print(
        "Gymnasium environments (model: the shipped value network a filter uses when given none; one that "
        "fails the trust bar needs allow_untrusted=True; reach pretrained shows its figures):"
    )
    for env_id, scene_name in reach_envs.ENV_SCENES.items():
        scene = SCENES[scene_name]()
        print(_line(env_id, f"scene={scene_name}", scene, agent_inputs(scene.system)))
    teams = []
    for env_id, fields in reach_envs.SYSTEM_ENVS.items():
        scene = env_scene(**fields)
        agents = agent_inputs(scene.system)
        source = f"scene={fields['scene']}" if "scene" in fields else f"system={fields['system']}"
        print(_line(env_id, source, scene, agents))
        if agents and "system" in fields:
            teams.append((fields["system"], agents))
    print(f'  {reach_envs.SYSTEM_ENV_ID:<28} any system: gym.make("{reach_envs.SYSTEM_ENV_ID}", system=...)')
    print(
        "Fleets of N cars (gym.make(id, n_cars=N); PettingZoo: reach_envs.fleet_envs.FleetParallelEnv(layout, "
        "n_cars=N); filter: safety.fleet.FleetFilter over the shipped pair grid pretrained:relativepair):"
    )
    for env_id, layout in reach_envs.FLEET_ENVS.items():
        print(f"  {env_id:<28} layout={layout:<14} kind=avoid cars=2..{MAX_CARS} action=N turn rates")
    print("Named scenes (gym.make(id, scene=NAME); reach_envs.parallel.parallel_env(NAME) where agents > 0):")
    for name, factory in SCENES.items():
        scene = factory()
        print(f"  {name:<20} system={scene.system.name:<25} agents={_agents(agent_inputs(scene.system))}")
    print("PettingZoo environments of systems (reach_envs.parallel.parallel_env(system=NAME), one team outcome):")
    for name, agents in teams:
        acts = ", ".join(f"{agent} acts inputs {list(inputs)}" for agent, inputs in agents.items())
        print(f"  {name:<20} {acts}")
    return 0
