"""``reach demo``: Air3D end to end (ground truth, training, verification, filter) into a report."""

from __future__ import annotations

import argparse
from typing import Any

from reach.validation import check_int, check_output_dir, positive_int_arg, seed_arg
from reach_cli.options import add_subparser, signature_default
from training.config import parse_duration


def add_parser(sub: Any) -> None:
    from studies.demo import DemoSettings, run_demo  # lazy: keeps `import reach_cli` light

    def d(name: str) -> Any:
        return signature_default(run_demo if name == "out" else DemoSettings, name)

    p = add_subparser(sub, "demo", help="Air3D end to end: ground truth, training, verification, filter, report")
    p.add_argument("--out", default=None, help=f"report directory (an interrupted demo resumes) (default: {d('out')})")
    p.add_argument(
        "--budget", default=None, help=f"training wall-clock budget, e.g. 90s, 3m (default: {d('budget_s'):g} s)"
    )
    p.add_argument(
        "--grid", type=positive_int_arg, default=None, help=f"ground-truth nodes per dimension (default: {d('grid')})"
    )
    p.add_argument(
        "--samples", type=positive_int_arg, default=None, help=f"verification rollouts (default: {d('samples')})"
    )
    p.add_argument(
        "--episodes", type=positive_int_arg, default=None, help=f"filter-evaluation episodes (default: {d('episodes')})"
    )
    p.add_argument("--seed", type=seed_arg, default=None, help=f"(default: {d('seed')})")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from studies.demo import DemoSettings, run_demo  # lazy: keeps `import reach_cli` light

    options: dict[str, Any] = {
        "grid": args.grid,
        "samples": args.samples,
        "episodes": args.episodes,
        "seed": args.seed,
        "budget_s": parse_duration(args.budget) if args.budget is not None else None,
    }
    options = {k: v for k, v in options.items() if v is not None}
    if "grid" in options:
        check_int("--grid", options["grid"], 5)
    settings = DemoSettings(**options)  # an option left out keeps DemoSettings' default
    out = args.out if args.out is not None else signature_default(run_demo, "out")
    check_output_dir(out, "--out")
    report = run_demo(out, settings)
    print(f"report: {report}")
    return 0
