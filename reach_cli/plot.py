"""``reach plot``: BRT slices, union-of-pairs overlays, violation bars or a filtered-episode GIF."""

from __future__ import annotations

import argparse
from typing import Any

from reach.systems import make_system
from reach.validation import check_output_path, finite_float_arg, nonnegative_float_arg, seed_arg
from reach.value_function import check_time_coverage
from reach_cli.options import add_subparser
from safety.value_loading import load_value_function


def add_parser(sub: Any) -> None:
    p = add_subparser(sub, "plot", help="BRT slices, union-of-pairs overlays, violation bars or a filtered-episode GIF")
    p.add_argument("kind", choices=["slices", "union", "bars", "episode"])
    p.add_argument("sources", nargs="+", help="value functions (slices, episode) or a results .json (bars)")
    p.add_argument("--ground-truth", default=None, help="grid .npz drawn as the reference BRT (slices)")
    p.add_argument("--pairwise", default=None, help="two-car grid .npz whose union is overlaid (union)")
    p.add_argument(
        "--slice",
        action="append",
        default=None,
        help="slice 'name=value,...;axis1,axis2', e.g. 'x2=-0.4,th1=pi/2;x1,y1' (repeatable; default per system)",
    )
    p.add_argument(
        "--t", type=finite_float_arg, default=None, help="time-to-go of the slices (default: the system's horizon)"
    )
    p.add_argument("--format", choices=["auto", "reach", "deepreach", "grid"], default="auto")
    p.add_argument("--system", default=None, help="system: a registered name or package.module:ClassName")
    p.add_argument("--layout", default=None)
    p.add_argument("--scene", default=None, help="scene of the episode (default: a plain scene of the source's system)")
    p.add_argument(
        "--threshold", type=nonnegative_float_arg, default=None, help="filter threshold (default: 2 x rate bound x dt)"
    )
    p.add_argument("--seed", type=seed_arg, default=0)
    p.add_argument("--out", required=True, help="PNG (slices, bars) or GIF (episode)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # lazy: this command's stack only when it runs
    from studies import plots
    from studies.batch_verification import expand_sources, load_results

    check_output_path(args.out, "--out")
    if args.kind == "bars":
        rows = load_results(args.sources[0])
        print(f"wrote {plots.plot_violation_bars(rows, args.out)}")
        return 0
    if args.kind == "episode":
        if args.system is not None:
            make_system(args.system)  # names the run's system module, so its import path loads
        summary = plots.record_filtered_episode(
            args.sources[0], args.out, scene=args.scene, threshold=args.threshold, seed=args.seed
        )
        print(f"wrote {summary['path']}: {summary['steps']} steps, collision={summary['collision']}")
        return 0
    loaded = [
        load_value_function(p, format=args.format, system=args.system, layout=args.layout)
        for p in expand_sources(args.sources)
    ]
    vfs = [(lv.label, lv.value_function) for lv in loaded]
    system = vfs[0][1].system
    for label, vf in vfs[1:]:
        system.require_same_physics(vf.system, f"{label} (one system a plot)")
    t = system.horizon if args.t is None else args.t
    for label, vf in vfs:
        check_time_coverage(vf, t, t, f"--t {t:g} ({label})")
    slices = [plots.parse_slice(s, system) for s in args.slice] if args.slice else None
    if args.kind == "union":
        if not args.pairwise:
            raise ValueError("plot union needs --pairwise PAIR.npz (reach groundtruth relativepair ...)")
        union = load_value_function(args.pairwise, format="grid", system=system).value_function
        print(f"wrote {plots.plot_union_overlay(vfs, union, args.out, slices=slices, t=args.t)}")
        return 0
    # the reference must be of the plotted system: a grid of another system is refused here
    reference = load_value_function(args.ground_truth, system=system).value_function if args.ground_truth else None
    if reference is not None:
        check_time_coverage(reference, t, t, f"--t {t:g} (ground truth)")
    print(f"wrote {plots.plot_brt_slices(vfs, args.out, t=args.t, slices=slices, reference=reference)}")
    return 0
