"""``reach export``: a safety filter as one ONNX file that runs without torch (:mod:`reach_runtime`).

Wiring only: the options become a :class:`~safety.filters.settings.FilterSettings` for
:func:`~safety.filters.export.export_filter`; options that set one of its fields default to ``None`` and
fall back to the dataclass.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from reach.atomic import atomic_path
from reach.validation import check_output_path, nonnegative_float_arg, positive_float_arg
from reach_cli.filter_eval import FILTER_OPTIONS, add_filter_options, parse_time_to_go
from reach_cli.options import add_subparser, default, signature_default
from safety.filters.export import export_filter
from safety.filters.settings import KINDS, FilterSettings


def add_parser(sub: Any) -> None:
    p = add_subparser(
        sub,
        "export",
        help="write a safety filter (value, gradient and decision) as one ONNX file for reach_runtime",
    )
    p.add_argument("source", help="value function: a run, .pt, pretrained:NAME, or min:A,B of networks")
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument(
        "--c",
        dest="c_file",
        default=None,
        metavar="FILE.c",
        help="also write the filter as one C file (reach_runtime.native: no ONNX Runtime, no Python; "
        "int reach_filter(n, state, time_to_go, u_nominal, outputs...))",
    )
    p.add_argument("--kind", choices=list(KINDS), default=default(FilterSettings, "kind"))
    p.add_argument(
        "--dt",
        type=positive_float_arg,
        default=None,
        help="control period in seconds: required for the lookahead, and sets the default threshold "
        "(2 x rate bound x dt for switch and smooth)",
    )
    p.add_argument(
        "--threshold", type=nonnegative_float_arg, default=None, help="filter threshold >= 0 (default: the rule above)"
    )
    p.add_argument(
        "--gamma", type=nonnegative_float_arg, default=None, help=f"smooth filter's barrier rate (default: "
        f"{default(FilterSettings, 'gamma'):g})"
    )  # fmt: skip
    p.add_argument(
        "--integrator",
        choices=["rk4", "euler"],
        default=signature_default(export_filter, "integrator"),
        help="how the lookahead and the greedy backup predict",
    )
    p.add_argument(
        "--time-to-go",
        default=None,
        help="the runtime's default time-to-go: None (the horizon), a number, or 'remaining' (the caller "
        "passes it; always so for reach kinds)",
    )
    add_filter_options(p)
    p.add_argument(
        "--check-states",
        type=int,
        default=signature_default(export_filter, "check_states"),
        help="sampled states the written file is checked on against the torch filter (0: none)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.check_states < 0:
        raise ValueError(f"--check-states must be >= 0, got {args.check_states}")
    if args.c_file is not None:
        _check_c_path(args.c_file)
    given = {field: getattr(args, field) for _, field, _, _ in FILTER_OPTIONS if getattr(args, field) is not None}
    if args.gamma is not None:
        given["gamma"] = args.gamma
    settings = FilterSettings(
        kind=args.kind, threshold=args.threshold, time_to_go=parse_time_to_go(args.time_to_go), **given
    )
    result = export_filter(
        args.source,
        args.out,
        settings,
        dt=args.dt,
        integrator=args.integrator,
        check_states=args.check_states,
    )
    meta = result.metadata
    print(
        f"wrote {result.path} ({result.path.stat().st_size / 1e6:.2f} MB): {meta['settings']['kind']} filter of "
        f"{meta['system_name']}, threshold {meta['settings']['threshold']:g}, backup {meta['settings']['policy']}, "
        f"source {meta['source']} ({meta['fingerprint'][:19]}...)"
    )
    print(f"trust bar: {meta['source_verdict']['line']}")
    if args.c_file is not None:
        from reach_runtime.native import c_source  # lazy: reads the graph with onnx, only for --c

        source = c_source(result.path)
        with atomic_path(args.c_file) as tmp, open(tmp, "w") as handle:
            handle.write(source)
        print(f"wrote {args.c_file} ({len(source) / 1e6:.2f} MB of C): {c_file_usage()}")
    if result.checked:
        print(
            f"checked on {result.checked} sampled states against the torch filter: "
            f"{result.checked - result.differing} equal decisions, {result.differing} differ within the "
            "threshold's rounding"
        )
    return 0


def c_file_usage() -> str:
    """How to call the written C file, in one line."""
    return (
        "call reach_filter_checked(n, state, time_to_go, u_nominal, control, value, gradient, intervened, "
        "infeasible, outside_domain, untrusted), which makes the runtime's checks and returns REACH_OK or why "
        "not; compile with -O3 -march=native -fno-math-errno -fno-trapping-math -lm (examples/c)"
    )


def _check_c_path(path: str) -> None:
    """Refuse a --c path that is not a writable .c file, before the export's work."""
    if Path(path).suffix != ".c":
        raise ValueError(f"--c must name a .c file, got {path!r}")
    check_output_path(path, "--c")
