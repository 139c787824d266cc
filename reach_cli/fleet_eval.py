"""``reach fleet-eval``: fleet filters against the fleet's size, in every fleet scene
(:mod:`studies.fleet_eval`); writes ``OUT.json``, ``.csv``, ``.md`` and, with ``--plot``, the figure."""

from __future__ import annotations

import argparse
from typing import Any

from reach.validation import check_output_path, csv_items, positive_int_arg, seed_arg
from reach_cli.options import add_subparser, default


def _csv(name: str) -> Any:
    def parse(text: str) -> tuple[str, ...]:
        return tuple(csv_items(name, text))

    return parse


def _sizes(text: str) -> tuple[int, ...]:
    out = []
    for item in csv_items("--sizes", text):
        try:
            out.append(int(item))
        except ValueError:
            raise argparse.ArgumentTypeError(f"--sizes: {item!r} is not an integer") from None
    return tuple(out)


def add_parser(sub: Any) -> None:
    from studies.fleet_settings import FleetEvalSettings  # lazy: keeps `import reach_cli` light

    p = add_subparser(sub, "fleet-eval", help="collisions, goals and decision time of fleet filters against N")
    p.add_argument("--out", required=True, help="results file stem: OUT.json, OUT.csv, OUT.md (a rerun continues it)")
    p.add_argument(
        "--layouts",
        type=_csv("--layouts"),
        default=None,
        help="fleet scenes (default: every one)",
    )
    p.add_argument(
        "--sizes",
        type=_sizes,
        default=None,
        help=f"fleet sizes (default: {','.join(map(str, default(FleetEvalSettings, 'sizes')))})",
    )
    p.add_argument(
        "--methods",
        type=_csv("--methods"),
        default=None,
        help=f"methods (default: {','.join(default(FleetEvalSettings, 'methods'))})",
    )
    p.add_argument(
        "--episodes",
        type=positive_int_arg,
        default=None,
        help=f"episodes per cell (default: {default(FleetEvalSettings, 'episodes')})",
    )
    p.add_argument(
        "--batch",
        type=positive_int_arg,
        default=None,
        help=f"episodes simulated at once (default: {default(FleetEvalSettings, 'batch')})",
    )
    ticks = default(FleetEvalSettings, "timing_ticks")
    p.add_argument(
        "--timing-ticks",
        type=int,
        default=None,
        help=f"decisions timed per cell at batch 1, one thread, from an episode's start; more than the episode has "
        f"times all of it (default: {ticks})",
    )
    p.add_argument(
        "--seed", type=seed_arg, default=None, help=f"episodes' seed (default: {default(FleetEvalSettings, 'seed')})"
    )
    p.add_argument(
        "--density",
        type=float,
        default=None,
        help=f"cars per unit area of the random-goals arena (default: {default(FleetEvalSettings, 'density')})",
    )
    p.add_argument(
        "--hold",
        type=float,
        default=None,
        help="seconds the fleet filter's greedy policy holds each candidate input (default: the filter's own)",
    )
    p.add_argument(
        "--reaction-time",
        type=float,
        default=None,
        help="seconds of a pair's closing speed the fleet filter's default threshold keeps in hand "
        "(default: the filter's own)",
    )
    p.add_argument(
        "--tie-break",
        default=None,
        help="how the fleet filter's greedy policy chooses among held inputs whose least pair value ties: the "
        "first, all straight (centre), or the one whose next least values are highest (leximin) (default: the "
        "filter's own)",
    )
    p.add_argument(
        "--keep-collisions",
        type=int,
        default=None,
        help="collided episodes kept per cell in OUT.collisions/, to replay with reach fleet-replay "
        f"(default: {default(FleetEvalSettings, 'keep_collisions')}; 0: none)",
    )
    p.add_argument("--plot", default=None, help="also draw collisions and goal rate against N to this PNG")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from studies.fleet_eval import run_fleet_eval  # lazy: keeps `import reach_cli` light
    from studies.fleet_plots import plot_fleet_eval  # lazy: matplotlib only when asked
    from studies.fleet_settings import FleetEvalSettings  # lazy: as above

    chosen = {
        "layouts": args.layouts,
        "sizes": args.sizes,
        "methods": args.methods,
        "episodes": args.episodes,
        "batch": args.batch,
        "timing_ticks": args.timing_ticks,
        "seed": args.seed,
        "density": args.density,
        "hold": args.hold,
        "reaction_time": args.reaction_time,
        "tie_break": args.tie_break,
        "keep_collisions": args.keep_collisions,
    }
    settings = FleetEvalSettings(**{k: v for k, v in chosen.items() if v is not None})
    out = args.out
    check_output_path(out + ".json", "--out")
    if args.plot is not None:
        check_output_path(args.plot, "--plot")
    rows = run_fleet_eval(settings, out, progress=lambda key: print(f"fleet-eval: {key}", flush=True))
    if args.plot is not None:
        plot_fleet_eval(rows, args.plot)
    print(f"{len(rows)} rows: {out}.md")
    return 0
