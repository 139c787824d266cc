"""``reach sweep``: train many layouts x seeds on one budget, score them along training, report.

Options that set a :class:`~studies.sweeps.spec.SweepSpec` field default to ``None`` and fall back to the
dataclass. Everything (spec, training options, ground truth's system, workers) is checked before
the ground truth is solved or any run is trained.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

from reach.validation import (
    csv_items,
    device_arg,
    finite_float_arg,
    nonnegative_int_arg,
    positive_int_arg,
    seed_arg,
)
from reach_cli.options import add_subparser, default
from training import parse_duration

#: (option, SweepSpec field, argparse keywords, help)
SPEC_OPTIONS: tuple[tuple[str, str, dict[str, Any], str], ...] = (
    ("--system", "system", {}, "system: a registered name or package.module:ClassName"),
    ("--steps", "steps", {"type": positive_int_arg}, "train a fixed number of steps instead of a budget"),
    ("--snapshots", "snapshots", {"type": positive_int_arg}, "score each run after every 1/N of its budget"),
    ("--width", "width", {"type": positive_int_arg}, "hidden width"),
    ("--device", "device", {"type": device_arg}, "cpu or cuda"),
    ("--evaluation", "evaluation", {"choices": ["auto", "groundtruth", "rollout"]}, "how snapshots are scored"),
    ("--grid", "grid", {"type": positive_int_arg}, "ground-truth grid nodes per dimension (solved once)"),
    ("--groundtruth", "groundtruth", {}, "an existing grid solution .npz to score against"),
    ("--eval-time", "eval_time", {"type": finite_float_arg}, "time to score at (None: the horizon)"),
    ("--samples", "samples", {"type": positive_int_arg}, "rollout evaluation: sampled states"),
    (
        "--scenario-samples",
        "scenario_samples",
        {"type": nonnegative_int_arg},
        "rollout evaluation: fresh states (0: skip)",
    ),
    (
        "--rollout-every",
        "rollout_every",
        {"type": positive_int_arg},
        "rollout evaluation: every k-th snapshot (+ last)",
    ),
    ("--eval-seed", "eval_seed", {"type": seed_arg}, "seed of the evaluation states"),
    ("--pairwise", "pairwise", {}, "rollout evaluation: two-car .npz for the union containment"),
)


def add_parser(sub: Any) -> None:
    from studies.sweeps.spec import SweepSpec  # lazy: keeps `import reach_cli` light

    p = add_subparser(
        sub,
        "sweep",
        threads=False,
        help="train many layouts x seeds on a budget, score them along training, write a report (resumable)",
    )
    for option, field, kwargs, text in SPEC_OPTIONS:
        p.add_argument(
            option, dest=field, default=None, help=f"{text} (default: {default(SweepSpec, field)})", **kwargs
        )
    p.add_argument("--layouts", default=None, help="comma-separated (default: the seed paper's layouts for the system)")
    p.add_argument("--seeds", default=None, help="a count (3 = seeds 0,1,2) or a list (0,4,7) (default: 0,1,2)")
    p.add_argument(
        "--budget",
        default=None,
        help=f"training wall-clock budget per run, e.g. 90s, 5m (default: {default(SweepSpec, 'budget_s'):g} s)",
    )
    p.add_argument(
        "--train", action="append", default=[], metavar="KEY=VALUE", help="other reach train options, e.g. points=4096"
    )
    p.add_argument("--backend", choices=["local", "ray"], default="local")
    p.add_argument("--address", default=None, help="ray: address of an existing cluster (default: start one)")
    p.add_argument("--workers", type=positive_int_arg, default=1, help="local: runs trained at once")
    p.add_argument(  # SUPPRESS: a `reach --threads N sweep` before the subcommand is not reset to None
        "--threads",
        type=positive_int_arg,
        default=argparse.SUPPRESS,
        help="torch threads per run (local default: cores/workers)",
    )
    p.add_argument("--out", required=True, help="sweep directory (an interrupted sweep continues there)")
    p.set_defaults(func=run)


def parse_seeds(text: str) -> list[int]:
    """``"3"`` means seeds 0, 1, 2; ``"0,4,7"`` lists them."""
    try:
        if "," in text:
            return [seed_arg(s) for s in csv_items("--seeds", text)]
        count = int(text)
    except (ValueError, argparse.ArgumentTypeError) as err:
        raise ValueError(f"--seeds must be a count (3) or a list of seeds (0,4,7), got {text!r}") from err
    if count < 1:
        raise ValueError(f"--seeds must be at least 1, got {count}")
    return list(range(count))


def parse_train_options(items: Sequence[str], option: str = "--train") -> dict[str, object]:
    """``KEY=VALUE`` training options; values are read as JSON where they parse, else as strings. An
    item without a key or ``=`` raises ``ValueError`` naming ``option``, the flag that gave it."""
    options: dict[str, object] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"{option} expects KEY=VALUE, got {item!r}")
        try:
            options[key.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            options[key.replace("-", "_")] = value
    return options


def run(args: argparse.Namespace) -> int:
    # lazy: this command's stack only when it runs
    from studies.sweeps.spec import SweepSpec, default_layouts
    from studies.sweeps.sweep import run_sweep

    fields: dict[str, Any] = {f: getattr(args, f) for _, f, _, _ in SPEC_OPTIONS if getattr(args, f) is not None}
    if args.budget is not None and args.steps is not None:
        raise ValueError("give --budget or --steps, not both")
    if args.budget is not None:
        fields["budget_s"] = parse_duration(args.budget)
    elif args.steps is not None:
        fields["budget_s"] = None
    system = fields.get("system", default(SweepSpec, "system"))
    if args.layouts:
        fields["layouts"] = csv_items("--layouts", args.layouts)
    else:
        fields["layouts"] = default_layouts(system)
    if args.seeds is not None:
        fields["seeds"] = parse_seeds(args.seeds)
    fields["train"] = parse_train_options(args.train)
    spec = SweepSpec(**fields)
    report, failed = run_sweep(
        spec, args.out, backend=args.backend, workers=args.workers, threads=args.threads, address=args.address
    )
    print(f"report: {report}")
    if failed:
        print(f"reach sweep: {len(failed)} of {len(spec.tasks())} runs failed (listed in the report)", file=sys.stderr)
        return 1
    return 0
