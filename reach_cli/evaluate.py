"""``reach evaluate``: verify value functions by rollouts on the same states, into one table.

Options that set a :class:`~safety.verification.verify.VerifySettings` field default to ``None`` and fall back to
the dataclass. Rows merge into an existing table at ``--out`` (same settings), so evaluating other
sources into it later, or from another process at the same time, keeps every row.
"""

from __future__ import annotations

import argparse
from typing import Any

from reach.validation import (
    check_output_path,
    device_arg,
    finite_float_arg,
    nonnegative_int_arg,
    positive_float_arg,
    positive_int_arg,
    probability_arg,
    seed_arg,
)
from reach_cli.options import add_subparser, default
from safety.verification.verify import VerifySettings

#: (option, VerifySettings field, argparse keywords, help)
VERIFY_OPTIONS: tuple[tuple[str, str, dict[str, Any], str], ...] = (
    ("--samples", "samples", {"type": positive_int_arg}, "uniform states, the same for every model"),
    (
        "--scenario-samples",
        "scenario_samples",
        {"type": nonnegative_int_arg},
        "fresh states for eps (None: --samples; 0 skips)",
    ),
    ("--beta", "beta", {"type": probability_arg}, "confidence parameter of the scenario guarantee"),
    ("--seed", "seed", {"type": seed_arg}, "seed of the sampled states"),
    ("--dt", "dt", {"type": positive_float_arg}, "rollout time step"),
    ("--integrator", "integrator", {"choices": ["euler", "rk4"]}, "rollout integrator"),
    (
        "--matmul-precision",
        "matmul_precision",
        {"choices": ["float32", "bfloat16"]},
        "bfloat16: networks' hidden products in bf16 during rollouts (faster, inexact; grids stay exact)",
    ),
    (
        "--policy",
        "policy",
        {"choices": ["gradient", "greedy"]},
        "the induced policy rolled out: the bang-bang u* of grad V, or the held candidate input that leaves the "
        "most value (slower)",
    ),
    (
        "--control-period",
        "control_period",
        {"type": positive_float_arg},
        "the policy decides every this many seconds and holds its input in between (a multiple of --dt; "
        "None: every step)",
    ),
    ("--horizon", "horizon", {"type": positive_float_arg}, "time-to-go of the check (None: the system's)"),
    (
        "--chunk-size",
        "chunk_size",
        {"type": positive_int_arg},
        "states rolled out at once; on a CUDA GPU 262144 unless given",
    ),
    ("--target-eps", "target_eps", {"type": probability_arg}, "robust scenario verification: eps to bound"),
    (
        "--robust-samples",
        "robust_samples",
        {"type": nonnegative_int_arg},
        "robust scenario set: fresh states to search and again to check (None: as --scenario-samples; 0 skips)",
    ),
    (
        "--share-samples",
        "share_samples",
        {"action": "store_true"},
        "the delta-level's check reuses the robust check's states in {V > delta} (the same guarantees from "
        "fewer rollouts)",
    ),
)


def add_parser(sub: Any) -> None:
    p = add_subparser(
        sub, "evaluate", help="verify value functions by rollouts: violations, delta-level, scenario guarantee"
    )
    p.add_argument(
        "sources",
        nargs="+",
        help="run directories, checkpoints (.pt), pretrained:NAME, DeepReach (.pth), grid (.npz), min:A,B, cap:A,B",
    )
    for option, field, kwargs, text in VERIFY_OPTIONS:
        p.add_argument(
            option, dest=field, default=None, help=f"{text} (default: {default(VerifySettings, field)})", **kwargs
        )
    p.add_argument("--format", choices=["auto", "reach", "deepreach", "grid"], default="auto")
    p.add_argument(
        "--system",
        default=None,
        help="system: a registered name or package.module:ClassName (needed for DeepReach files; "
        "lets a run of a user system import its module)",
    )
    p.add_argument("--layout", default=None, help="layout (needed for DeepReach files)")
    p.add_argument("--ground-truth", default=None, help="grid .npz to score IoU and MSE against")
    p.add_argument(
        "--gt-time", type=finite_float_arg, default=None, help="time of that comparison (default: last stored)"
    )
    p.add_argument(
        "--pairwise", default=None, help="two-car grid .npz (reach groundtruth relativepair): containment metric"
    )
    p.add_argument("--device", type=device_arg, default="cpu")
    p.add_argument(
        "--backend",
        choices=["local", "ray"],
        default="local",
        help="where the rollout blocks run: this process, or Ray tasks (a local instance, or --address); same rows",
    )
    p.add_argument("--address", default=None, help="the Ray cluster to run the blocks on (--backend ray)")
    p.add_argument("--plot", action="store_true", help="also draw a bar chart of violation rates")
    p.add_argument("--out", default="results.csv", help="results path; .csv, .json and .md are written")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # lazy: this command's stack only when it runs
    from safety.verification.rollout import default_chunk_size
    from safety.verification.sharding import make_backend
    from studies.batch_verification import SourceLoading, evaluate_many, markdown_table, report_failures
    from studies.plots import plot_violation_bars

    given = {field: getattr(args, field) for _, field, _, _ in VERIFY_OPTIONS if getattr(args, field) is not None}
    given.setdefault("chunk_size", default_chunk_size(args.device))  # a GPU fills up only with larger blocks
    settings = VerifySettings(**given)
    out = check_output_path(args.out, "--out")
    backend = make_backend(args.backend, args.address)  # refuses --address without ray, before any work
    try:
        rows = evaluate_many(
            args.sources,
            out,
            settings,
            loading=SourceLoading(system=args.system, format=args.format, layout=args.layout),
            ground_truth=args.ground_truth,
            gt_time=args.gt_time,
            pairwise=args.pairwise,
            device=args.device,
            backend=backend,
        )
    finally:
        if backend is not None:
            backend.close()
    print(markdown_table(rows))
    print(f"\nwrote {out.with_suffix('.csv')}, {out.with_suffix('.json')}, {out.with_suffix('.md')}")
    if args.plot and any(not r.get("error") for r in rows):
        print(f"wrote {plot_violation_bars(rows, out.with_name(out.stem + '_violations.png'))}")
    return report_failures(rows, "reach evaluate")
