"""``reach train``: train a value network of any activation layout, or resume a run.

Every option that sets a :class:`~training.config.TrainConfig` field defaults to ``None`` and falls
back to the dataclass, whose defaults ``--help`` prints. ``--resume RUN`` continues a run with its
stored configuration: it takes new stop rules (``--steps``, ``--budget``, ``--target-loss``), logging
options and ``--device``; any other training option is refused rather than silently ignored.

``--distributed`` trains one run in the processes ``torchrun`` starts (:mod:`training.distributed`):
``torchrun --nproc-per-node N -m reach train --distributed ...``. Every process runs this command;
rank 0 alone writes the run directory and prints.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from typing import Any

from groundtruth import GridSolution
from reach.exit_codes import EXIT_PARTIAL
from reach.validation import (
    device_arg,
    finite_float_arg,
    nonnegative_float_arg,
    nonnegative_int_arg,
    positive_float_arg,
    positive_int_arg,
    seed_arg,
    unit_interval_arg,
)
from reach_cli.options import add_subparser, default
from training import TrainConfig, Trainer, TrainingDivergedError, parse_duration
from training.distributed import JOIN_TIMEOUT_S, Processes, joined
from training.network import PARAMETERISATIONS
from training.run_directory import RESUME_OVERRIDABLE, RunDirectory


def _optional_float(text: str) -> float | str:
    """A positive number, or ``"off"``."""
    if text.strip().lower() == "off":
        return "off"
    return positive_float_arg(text)


#: (option, TrainConfig field, argparse keywords, help): the options that set a training field
TRAIN_OPTIONS: tuple[tuple[str, str, dict[str, Any], str], ...] = (
    ("--system", "system", {}, "system: a registered name or package.module:ClassName"),
    ("--layout", "layout", {}, "one letter per activated layer (s sine, r ReLU, t tanh, g GELU) and a final l"),
    ("--width", "width", {"type": positive_int_arg}, "hidden width"),
    ("--w0", "w0", {"type": positive_float_arg}, "sine frequency"),
    (
        "--parameterisation",
        "parameterisation",
        {"choices": list(PARAMETERISATIONS)},
        "exact: V(x, 0) = l(x) by design; exact-constraint (reach-avoid): also V >= -g",
    ),
    (
        "--sincos",
        "sincos",
        {"action": argparse.BooleanOptionalAction},
        "encode headings as (sin, cos) (--no-sincos: heading / pi, with a seam at +-pi)",
    ),
    ("--sincos-radius", "sincos_radius", {"type": positive_float_arg}, "scale of the (sin, cos) inputs"),
    (
        "--points",
        "points",
        {"type": positive_int_arg},
        "points per step, in all (--distributed splits them evenly among the processes)",
    ),
    ("--lr", "lr", {"type": positive_float_arg}, "learning rate"),
    ("--lr-final", "lr_final", {"type": positive_float_arg}, "final learning rate of the cosine schedule"),
    ("--schedule", "schedule", {"choices": ["cosine", "constant"]}, "learning-rate schedule"),
    ("--loss", "loss", {"choices": ["l1", "l2"]}, "norm of the HJI residual"),
    (
        "--gradient-bound",
        "gradient_bound",
        {"type": _optional_float},
        "penalise |dV/dx| above this many times l's steepest slope (normalised coordinates; removes cliffs; "
        "'off' disables)",
    ),
    ("--gradient-weight", "gradient_weight", {"type": nonnegative_float_arg}, "weight of the gradient-bound penalty"),
    (
        "--upper-bound",
        "upper_bound",
        {},
        "multi-vehicle systems: a pair grid solution (.npz, or the shipped pretrained:relativepair) whose union "
        "of pairwise values V may not exceed (penalised where a pair's grid covers the state)",
    ),
    ("--upper-bound-weight", "upper_bound_weight", {"type": nonnegative_float_arg}, "weight of that penalty"),
    (
        "--lower-bound",
        "lower_bound",
        {"choices": ["policy", "mpc"]},
        "systems without a disturbance: penalise V below what the network's own policy achieves from "
        "sampled states (policy: rollout labels, a lower bound of V; mpc: the best of sampled control "
        "sequences over a short horizon, bootstrapped by the network's value at its end)",
    ),
    ("--lower-bound-weight", "lower_bound_weight", {"type": nonnegative_float_arg}, "weight of that penalty"),
    ("--lower-bound-points", "lower_bound_points", {"type": positive_int_arg}, "states labelled per refresh"),
    ("--lower-bound-every", "lower_bound_every", {"type": positive_int_arg}, "steps between label refreshes"),
    ("--lower-bound-dt", "lower_bound_dt", {"type": positive_float_arg}, "step of the labelling rollouts (RK4)"),
    ("--lower-bound-samples", "lower_bound_samples", {"type": positive_int_arg}, "mpc: control sequences per state"),
    ("--lower-bound-horizon", "lower_bound_horizon", {"type": positive_float_arg}, "mpc: their horizon (s)"),
    (
        "--lower-bound-noise",
        "lower_bound_noise",
        {"type": nonnegative_float_arg},
        "mpc: their perturbation of u* (Gaussian, times the input box's half-width)",
    ),
    (
        "--zero-level-fraction",
        "zero_level_fraction",
        {"type": unit_interval_arg},
        "share of each step's points drawn near the network's zero level (the smallest |V| of a larger uniform draw)",
    ),
    (
        "--zero-level-candidates",
        "zero_level_candidates",
        {"type": positive_int_arg},
        "uniform draws per zero-level point (at least 2)",
    ),
    (
        "--gradients",
        "gradients",
        {"choices": ["fused", "autograd"]},
        "input derivatives: carried through the layers by hand (one backward) or by autograd (double backward)",
    ),
    ("--curriculum", "curriculum", {"type": unit_interval_arg}, "share of the run over which t grows to T"),
    ("--pretrain", "pretrain", {"type": unit_interval_arg}, "vanilla: share of the run on the boundary only"),
    ("--steps", "steps", {"type": positive_int_arg}, "stop after this many steps"),
    ("--target-loss", "target_loss", {"type": positive_float_arg}, "stop when the loss average falls to this"),
    ("--seed", "seed", {"type": seed_arg}, "seed of the network's initialisation and the sampling"),
    ("--device", "device", {"type": device_arg}, "cpu or cuda"),
    ("--log-every", "log_every", {"type": positive_int_arg}, "steps between metric lines"),
    ("--checkpoint-every", "checkpoint_every_s", {"type": nonnegative_float_arg}, "seconds between checkpoints"),
    ("--eval-every", "eval_every_s", {"type": nonnegative_float_arg}, "seconds between evaluations"),
    ("--snapshots", "snapshots", {"type": nonnegative_int_arg}, "save the network after every 1/N of the run"),
)


#: the choices of --compile and --cuda-graph, and the TrainConfig value each stands for (None: auto)
AUTO_ON_OFF = {"auto": None, "on": True, "off": False}


def train_flags(fields: dict[str, Any]) -> list[str]:
    """The ``reach train`` options that set these :class:`~training.TrainConfig` fields, for a script
    that prints or runs the command (a field's flag is not always its name: ``checkpoint_every_s`` is
    ``--checkpoint-every``). A field no option sets raises ``ValueError`` naming it."""
    flags = {field: flag for flag, field, _, _ in TRAIN_OPTIONS}
    missing = sorted(set(fields) - set(flags))
    if missing:
        raise ValueError(f"no reach train option sets {', '.join(missing)}")
    return [item for field, value in fields.items() for item in (flags[field], str(value))]


def add_parser(sub: Any) -> None:
    p = add_subparser(sub, "train", help="train a value network of any activation layout")
    add_training_options(p)
    p.add_argument("--budget", default=None, help="wall-clock budget, e.g. 90s, 10m, 1h (default: none)")
    p.add_argument(
        "--compile",
        choices=list(AUTO_ON_OFF),
        default=None,
        help="torch.compile the training step (auto, the default: runs of 2 min or 2000 steps and more, eager if "
        "compiling fails)",
    )
    p.add_argument(
        "--cuda-graph",
        choices=list(AUTO_ON_OFF),
        default=None,
        help="replay each step as one CUDA graph (auto, the default: on a CUDA device, for runs that allow it; "
        "on: refuse runs that do not, naming why)",
    )
    p.add_argument(
        "--tf32",
        action="store_true",
        default=None,
        help="let a CUDA GPU's TF32 tensor cores do the float32 matrix products (faster, not exact)",
    )
    p.add_argument(
        "--tensorboard", action="store_true", default=None, help="also log metrics for TensorBoard in RUN/tensorboard"
    )
    p.add_argument("--groundtruth", default=None, help="grid solution .npz to evaluate against while training")
    p.add_argument("--eval-time", type=finite_float_arg, default=None, help="time of evaluation (default: last stored)")
    p.add_argument("--out", default=None, help="run directory for a new run")
    p.add_argument("--resume", default=None, metavar="RUN_DIR", help="continue the run in RUN_DIR")
    p.add_argument(
        "--distributed",
        action="store_true",
        help="train one run in the processes torchrun starts (torchrun --nproc-per-node N -m reach train "
        "--distributed ...): each takes an even share of every step's points, DistributedDataParallel averages "
        "their gradients (gloo on the CPU, NCCL on CUDA, a GPU per process); rank 0 alone writes the run",
    )
    p.add_argument(
        "--join-timeout",
        type=positive_float_arg,
        default=JOIN_TIMEOUT_S,
        metavar="SECONDS",
        help="--distributed: how long each process waits for all the others to join (default: %(default)g)",
    )
    p.set_defaults(func=run)


def add_training_options(p: argparse.ArgumentParser, skip: frozenset[str] = frozenset()) -> None:
    """Every option of :data:`TRAIN_OPTIONS` but the fields ``skip``, with its default in its help
    (``reach train``'s, and ``reach train-until``'s for the runs it starts)."""
    for option, field, kwargs, text in TRAIN_OPTIONS:
        if field not in skip:
            value = default(TrainConfig, field)
            p.add_argument(option, dest=field, default=None, help=f"{text} (default: {value})", **kwargs)


def training_fields(args: argparse.Namespace) -> dict[str, Any]:
    """The TrainConfig fields of :data:`TRAIN_OPTIONS` the user set on the command line (``--gradient-bound
    off``: ``None``); options a parser did not add count as not set."""
    fields = {field: getattr(args, field, None) for _, field, _, _ in TRAIN_OPTIONS}
    fields = {field: value for field, value in fields.items() if value is not None}
    if fields.get("gradient_bound") == "off":
        fields["gradient_bound"] = None
    return fields


def _config_fields(args: argparse.Namespace) -> dict[str, Any]:
    """The TrainConfig fields the user set on the command line."""
    fields = training_fields(args)
    if args.budget is not None:
        fields["budget_s"] = parse_duration(args.budget)
    for option in ("compile", "cuda_graph"):
        if getattr(args, option) is not None:
            fields[option] = AUTO_ON_OFF[getattr(args, option)]
    if args.tf32:
        fields["matmul_precision"] = "tf32"
    if args.tensorboard:
        fields["tensorboard"] = True
    return fields


def _evaluator(args: argparse.Namespace) -> Any:
    if not args.groundtruth:
        return None
    from training.accuracy import ReferenceEvaluator  # lazy: the evaluator only with --groundtruth

    reference = GridSolution.load(args.groundtruth, outside="clamp")
    t_eval = args.eval_time if args.eval_time is not None else float(reference.times[-1])
    return ReferenceEvaluator(reference, t_eval)


def run(args: argparse.Namespace) -> int:
    fields = _config_fields(args)
    if args.resume:
        config = _resumed_config(args, fields)
    else:
        if not args.out:
            raise ValueError("give --out RUN_DIR for a new run (or --resume RUN_DIR)")
        config = TrainConfig(**fields).validate()  # before loading a ground truth or building anything
    # --distributed: torchrun's environment, the device and the batch's shares are checked before joining
    with joined(config, args.join_timeout) if args.distributed else contextlib.nullcontext(Processes()) as processes:
        evaluator = _evaluator(args) if processes.main else None  # rank 0 evaluates and reports
        if args.resume:
            trainer = Trainer.resume(args.resume, evaluator=evaluator, processes=processes, **fields)
        else:
            trainer = Trainer(config, args.out, evaluator=evaluator, processes=processes)
        try:
            summary = trainer.train()
        except TrainingDivergedError as err:
            if processes.main:
                print(f"reach train: {err}", file=sys.stderr)
            return EXIT_PARTIAL
    if processes.main:
        print(
            f"{summary['run_dir']}: {summary['steps']} steps in {summary['wall_time_s']:.1f} s ({summary['stopped']})"
        )
    return 0


def _resumed_config(args: argparse.Namespace, fields: dict[str, Any]) -> TrainConfig:
    """The configuration ``--resume`` continues with, its options checked before the ground truth loads."""
    if args.out:
        raise ValueError(f"give --out for a new run or --resume for an old one, not both (--out {args.out})")
    # an option the run cannot change is refused, naming its flag, unless it restates the stored
    # value (``--compile off`` on a run trained with it); checked before the ground truth loads
    refuse_changes(args.resume, fields, RESUME_OVERRIDABLE, "--resume continues", "start a new run with --out")
    return RunDirectory(args.resume).resumed_config(fields)[0]


def refuse_changes(run_dir: str, fields: dict[str, Any], may_change: frozenset[str], what: str, instead: str) -> None:
    """Refuse, naming each flag with its given and stored values, the ``fields`` (TrainConfig fields
    from the command line) that differ from the run in ``run_dir``'s stored configuration, but for
    ``may_change``; a field that restates its stored value is not a change. ``what`` and ``instead``
    word the error (``"--resume continues"``, ``"start a new run with --out"``)."""
    stored, _ = RunDirectory(run_dir).resumed_config({})
    fixed = sorted(k for k in set(fields) - may_change if getattr(stored, k) != fields[k])
    if fixed:
        option = {field: flag for flag, field, _, _ in TRAIN_OPTIONS} | {"budget_s": "--budget", "compile": "--compile"}
        names = ", ".join(f"{option.get(k, k)} {fields[k]!r} (stored: {getattr(stored, k)!r})" for k in fixed)
        raise ValueError(
            f"{what} {run_dir} with its stored configuration; {names} cannot change ({instead} to train with "
            "other settings)"
        )
