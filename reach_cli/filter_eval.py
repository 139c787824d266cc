"""``reach filter-eval``: episodes of a goal-seeking task with and without the safety filter."""

from __future__ import annotations

import argparse
from typing import Any

from reach.validation import (
    check_float,
    check_output_path,
    csv_floats,
    nonnegative_float_arg,
    positive_int_arg,
    seed_arg,
)
from reach_cli.options import add_subparser
from safety.filter import DEFAULT_GAMMA, KINDS


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
    p.add_argument("--episodes", type=positive_int_arg, default=1000)
    p.add_argument("--seed", type=seed_arg, default=0)
    p.add_argument(
        "--thresholds", default=None, help="comma-separated filter thresholds >= 0 (default: 2 x rate bound x dt)"
    )
    p.add_argument(
        "--filters",
        default="switch",
        help="comma-separated filter kinds to compare on the same episodes: switch, lookahead, smooth",
    )
    p.add_argument(
        "--gammas",
        default=None,
        help=f"smooth filter: comma-separated barrier rates gamma >= 0 (default: {DEFAULT_GAMMA:g})",
    )
    p.add_argument(
        "--backup-horizon",
        type=nonnegative_float_arg,
        default=None,
        help="lookahead filter: seconds of the backup policy checked after the nominal step "
        "(default: the system's horizon)",
    )
    p.add_argument(
        "--backup-disturbance",
        choices=["robust", "model"],
        default="robust",
        help="lookahead filter: check the value function's d* path and a greedy worst case over the "
        "disturbance box's corners (robust), or the d* path alone (model)",
    )
    p.add_argument(
        "--policy",
        choices=["gradient", "greedy"],
        default=None,
        help="the input a filter applies when it overrides the nominal one: the bang-bang u* of grad V "
        "(gradient), or the candidate input held for a short step that leaves the most value (greedy); "
        "default: greedy for switch, gradient for lookahead and smooth",
    )
    p.add_argument("--time-to-go", default=None, help="None (value function horizon), a number, or 'remaining'")
    p.add_argument("--pursuer", choices=["scene", "pursue", "random", "worst-case"], default="scene")
    p.add_argument("--adversary", default=None, help="value function whose d* the worst-case pursuer plays")
    p.add_argument("--start-outside", default=None, help="value function: start only from {V > margin}")
    p.add_argument("--start-margin", type=nonnegative_float_arg, default=0.1)
    p.add_argument(
        "--start-from",
        choices=["domain", "scene"],
        default="domain",
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
    from reach_envs.scenes import env_scene
    from safety.sources import load_value_function
    from studies.batch_verification import expand_sources
    from studies.filter_eval import filter_table, run_filter_study

    # checks first: scene, numbers, output paths, then the value functions (their time ranges too)
    # a named scene or a plain scene of --system (not both); air3d when neither is given
    scene = env_scene(args.scene if args.scene or args.system else "air3d", args.system)
    system = scene.system
    nominal = None
    if args.nominal is not None:
        from reach.systems.registry import import_object

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
    gammas = csv_floats("--gammas", args.gammas, lambda n, v: check_float(n, v, 0)) if args.gammas else [DEFAULT_GAMMA]
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
    study = run_filter_study(
        scene,
        [(lv.label, lv.value_function) for lv in loaded],
        out,
        thresholds=thresholds,
        episodes=args.episodes,
        seed=args.seed,
        time_to_go=ttg,
        pursuer=pursuer,
        start_outside=start,
        start_margin=args.start_margin,
        start_from=args.start_from,
        gif=args.gif,
        pettingzoo=args.pettingzoo,
        kinds=kinds,
        gammas=gammas,
        nominal=nominal,
        backup_horizon=args.backup_horizon,
        backup_disturbance=args.backup_disturbance,
        policy=args.policy,
        merge=True,  # rows join a table of the same episodes already at --out, as reach evaluate's do
        header={
            "filters": kinds,
            "gammas": gammas if "smooth" in kinds else None,
            "backup_horizon": args.backup_horizon if "lookahead" in kinds else None,
            "backup_disturbance": args.backup_disturbance if "lookahead" in kinds else None,
            "policy": args.policy,
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
        },
    )
    print(filter_table(study.rows))
    print()
    for path in study.paths:
        note = f" (nominal, then filtered by {loaded[0].label}: {', '.join(kinds)})" if path == args.gif else ""
        print(f"wrote {path}{note}")
    return 0
