"""``reach filter-eval``: episodes of a goal-seeking task with and without the safety filter.

Wiring only: the options become a :class:`~studies.filter_configs.FilterStudySettings` (its episodes,
its filter grid with one shared :class:`~safety.filters.settings.FilterSettings`, its outputs) for
:func:`~studies.filter_study.run_filter_study`. Options that set a ``FilterSettings`` field default
to ``None`` and fall back to the dataclass; every other default is read from the dataclasses too.
"""

from __future__ import annotations

import argparse
from typing import Any

from reach.systems.registry import import_object
from reach.validation import (
    check_float,
    check_output_path,
    csv_floats,
    nonnegative_float_arg,
    positive_int_arg,
    seed_arg,
)
from reach_cli.options import add_subparser, default
from safety.filters.settings import KINDS, LOOKAHEAD_DISTURBANCES, OUTSIDE_DOMAIN, FilterSettings
from safety.value_loading import load_value_function
from safety.value_policies import POLICIES
from studies.filter_configs import START_FROM, EpisodeSettings, FilterGrid, FilterStudySettings, StudyOutput

#: (option, FilterSettings field, argparse keywords, help): options shared by every filter of the run
FILTER_OPTIONS: tuple[tuple[str, str, dict[str, Any], str], ...] = (
    (
        "--backup-horizon",
        "backup_horizon",
        {"type": nonnegative_float_arg},
        "lookahead filter: seconds of the backup policy checked after the nominal step (None: the system's horizon)",
    ),
    (
        "--backup-disturbance",
        "backup_disturbance",
        {"choices": list(LOOKAHEAD_DISTURBANCES)},
        "lookahead filter: check the value function's d* path and a greedy worst case over the "
        "disturbance box's corners (robust), or the d* path alone (model)",
    ),
    (
        "--policy",
        "policy",
        {"choices": list(POLICIES)},
        "the input a filter applies when it overrides the nominal one: the bang-bang u* of grad V "
        "(gradient), or the candidate input held for a short step that leaves the most value (greedy); "
        "None: greedy for switch, gradient for lookahead and smooth",
    ),
    (
        "--outside-domain",
        "outside_domain",
        {"choices": list(OUTSIDE_DOMAIN)},
        "at a state outside the value function's domain: keep no nominal input and apply the backup "
        "input (backup, fail closed), or decide on the extrapolated V (extrapolate)",
    ),
)


def add_filter_options(p: argparse.ArgumentParser) -> None:
    """The :data:`FILTER_OPTIONS` on ``p``, each defaulting to None (the dataclass's default, shown)."""
    for option, field, kwargs, text in FILTER_OPTIONS:
        p.add_argument(
            option, dest=field, default=None, help=f"{text} (default: {default(FilterSettings, field)})", **kwargs
        )


def add_parser(sub: Any) -> None:

    p = add_subparser(
        sub, "filter-eval", help="episodes of a goal-seeking task with and without the safety filter: safety vs task"
    )
    p.add_argument(
        "value_functions",
        nargs="*",
        help="value functions to filter with (runs, .pt, pretrained:NAME, .pth, .npz, min:A,B, cap:A,B)",
    )
    p.add_argument(
        "--scene", default=None, help="named scene (air3d, three-car-merge, three-car-crossing, ...; default air3d)"
    )
    p.add_argument(
        "--system",
        default=None,
        help="instead of --scene: a plain scene of this system (registered name or package.module:ClassName)",
    )
    p.add_argument(
        "--nominal",
        default=None,
        help="nominal policy package.module:function, states (N, n) -> actions (N, m) in [-1, 1] "
        "(default: the scene's goal task; for a system without goals, the centre of the control box)",
    )
    p.add_argument("--episodes", type=positive_int_arg, default=default(EpisodeSettings, "episodes"))
    p.add_argument("--seed", type=seed_arg, default=default(EpisodeSettings, "seed"))
    p.add_argument(
        "--thresholds", default=None, help="comma-separated filter thresholds >= 0 (default: 2 x rate bound x dt)"
    )
    p.add_argument(
        "--filters",
        default=default(FilterSettings, "kind"),
        help=f"comma-separated filter kinds to compare on the same episodes: {', '.join(KINDS)} "
        f"(default: {default(FilterSettings, 'kind')})",
    )
    p.add_argument(
        "--gammas",
        default=None,
        help=f"smooth filter: comma-separated barrier rates gamma >= 0 (default: {default(FilterSettings, 'gamma'):g})",
    )
    add_filter_options(p)
    p.add_argument(
        "--time-to-go",
        default=None,
        help="None (value function horizon), a number, or 'remaining' "
        f"(default: {default(FilterSettings, 'time_to_go')})",
    )
    p.add_argument("--pursuer", choices=["scene", "pursue", "random", "worst-case"], default="scene")
    p.add_argument("--adversary", default=None, help="value function whose d* the worst-case pursuer plays")
    p.add_argument("--start-outside", default=None, help="value function: start only from {V > margin}")
    p.add_argument("--start-margin", type=nonnegative_float_arg, default=default(EpisodeSettings, "start_margin"))
    p.add_argument(
        "--start-from",
        choices=list(START_FROM),
        default=default(EpisodeSettings, "start_from"),
        help="--start-outside draws uniformly over the system's domain, or among the scene's own starts",
    )
    p.add_argument("--format", choices=["auto", "reach", "deepreach", "grid"], default="auto")
    p.add_argument("--layout", default=None, help="layout (needed for DeepReach files)")
    p.add_argument("--pettingzoo", action="store_true", help="run through the PettingZoo parallel env instead")
    p.add_argument(
        "--gif", default=None, help="also write a GIF of 3 episodes: nominal and each filter kind, side by side"
    )
    p.add_argument("--out", default="filter.csv", help="results path; .csv, .json and .md are written")
    p.set_defaults(func=run)


def parse_time_to_go(text: str | None) -> float | str | None:
    """``None`` (the value function's horizon), ``"remaining"``, or a number >= 0."""
    if text is None or text == "remaining":
        return text
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--time-to-go must be a number or 'remaining', got {text!r}") from None
    return check_float("--time-to-go", value, 0)


def run(args: argparse.Namespace) -> int:
    # lazy: this command's stack only when it runs
    from reach_envs.scenes import env_scene
    from studies.batch_verification import expand_sources
    from studies.filter_study import run_filter_study
    from studies.filter_tables import filter_table

    # checks first: scene, numbers, output paths, then the value functions (their time ranges too)
    # a named scene or a plain scene of --system (not both); air3d when neither is given
    scene = env_scene(args.scene if args.scene or args.system else "air3d", args.system)
    system = scene.system
    nominal = None
    if args.nominal is not None:
        nominal = import_object(args.nominal, what="--nominal")
        if not callable(nominal):
            raise ValueError(f"--nominal {args.nominal!r} is not callable")
    ttg = parse_time_to_go(args.time_to_go)
    thresholds = (
        csv_floats("--thresholds", args.thresholds, lambda n, v: check_float(n, v, 0)) if args.thresholds else [None]
    )
    kinds = [k.strip() for k in args.filters.split(",") if k.strip()]
    unknown = [k for k in kinds if k not in KINDS]
    if unknown or not kinds:
        raise ValueError(f"--filters must list kinds among {', '.join(KINDS)}, got {args.filters!r}")
    gammas = (
        csv_floats("--gammas", args.gammas, lambda n, v: check_float(n, v, 0))
        if args.gammas
        else [default(FilterSettings, "gamma")]
    )
    given = {field: getattr(args, field) for _, field, _, _ in FILTER_OPTIONS if getattr(args, field) is not None}
    shared = FilterSettings(time_to_go=ttg, **given)  # what every filter of the run shares
    grid = FilterGrid(thresholds, kinds, gammas, shared)
    out = check_output_path(args.out, "--out")
    if args.gif:
        check_output_path(args.gif, "--gif")
    loaded = [
        load_value_function(p, format=args.format, system=system, layout=args.layout)
        for p in (expand_sources(args.value_functions) if args.value_functions else [])
    ]
    pursuer = None
    if args.pursuer != "scene":
        if not system.disturbance_dim:
            raise ValueError(f"--pursuer {args.pursuer}: scene {scene.name} has no disturbance input")
        pursuer = args.pursuer
        if args.pursuer == "worst-case":
            source = args.adversary or (str(loaded[0].path) if loaded else None)
            if source is None:
                raise ValueError("--pursuer worst-case needs --adversary VF (or a value function to filter with)")
            pursuer = load_value_function(source, system=system).value_function
    start = load_value_function(args.start_outside, system=system).value_function if args.start_outside else None
    episodes = EpisodeSettings(
        episodes=args.episodes,
        seed=args.seed,
        pursuer=pursuer,
        start_outside=start,
        start_margin=args.start_margin,
        start_from=args.start_from,
        nominal=nominal,
        pettingzoo=args.pettingzoo,
    )
    header = {
        "filters": kinds,
        "gammas": gammas if "smooth" in kinds else None,
        "backup_horizon": shared.backup_horizon if "lookahead" in kinds else None,
        "backup_disturbance": shared.backup_disturbance if "lookahead" in kinds else None,
        "policy": shared.policy,
        "format": "reach.filter-eval.v1",
        "scene": scene.name,
        "system": system.reference(),
        "nominal": args.nominal or "task default",
        "pursuer": args.pursuer,
        "time_to_go": args.time_to_go or "value function horizon",
        "start_outside": args.start_outside,
        "start_margin": args.start_margin if args.start_outside else None,
        "start_from": args.start_from if args.start_outside else None,
        "path": "pettingzoo" if args.pettingzoo else "vector",
    }
    # rows join a table of the same episodes already at --out, as reach evaluate's do
    output = StudyOutput(gif=args.gif, header=header, merge=True)
    sources = [(lv.label, lv.value_function) for lv in loaded]
    study = run_filter_study(scene, sources, out, FilterStudySettings(episodes, grid, output))
    print(filter_table(study.rows))
    print()
    for path in study.paths:
        note = f" (nominal, then filtered by {loaded[0].label}: {', '.join(kinds)})" if path == args.gif else ""
        print(f"wrote {path}{note}")
    return 0
