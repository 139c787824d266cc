"""``reach train-until``: train in phases, each verified on fresh states, until the scenario bound holds
(:mod:`studies.train_until`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from reach.validation import (
    check_output_dir,
    nonnegative_float_arg,
    positive_float_arg,
    positive_int_arg,
    seed_arg,
    unit_interval_arg,
)
from reach_cli.options import add_subparser, default
from reach_cli.train import add_training_options, refuse_changes, training_fields
from training.config import TrainConfig, parse_duration

#: the options that set TrainUntilSettings' fields: (flag, field, type, help)
SETTINGS_OPTIONS = (
    ("--phase-steps", "phase_steps", positive_int_arg, "training steps per phase"),
    ("--max-phases", "max_phases", positive_int_arg, "at most this many phases"),
    ("--target-eps", "target_eps", positive_float_arg, "the scenario bound to reach"),
    ("--max-wrong-rate", "max_wrong_rate", unit_interval_arg, "the highest share of wrong claims that holds"),
    ("--samples", "samples", positive_int_arg, "fresh states each phase's verification rolls out"),
    ("--scenario-samples", "scenario_samples", positive_int_arg, "states that check the delta-level's bound"),
    ("--final-samples", "final_samples", positive_int_arg, "the final verification's states"),
    ("--verify-seed", "seed", seed_arg, "the verifications' seed"),
    ("--hard-fraction", "hard_fraction", unit_interval_arg, "share of each step's points near the hard states"),
    ("--dt", "dt", positive_float_arg, "the rollouts' step, in seconds"),
    (
        "--refuted-weight",
        "refuted_weight",
        nonnegative_float_arg,
        "weight of the term that keeps the network from claiming success along its failed rollouts",
    ),
    ("--refuted-margin", "refuted_margin", nonnegative_float_arg, "how far past zero those claims are pushed"),
)

#: the training options train-until does not take: each phase sets its own steps, and the loop stops
STOP_RULES = frozenset({"steps", "target_loss"})


def add_parser(sub: Any) -> None:
    from studies.train_until import TrainUntilSettings  # lazy: keeps `import reach_cli` light

    p = add_subparser(
        sub, "train-until", help="train in phases, each verified on fresh states, until the scenario bound holds"
    )
    p.add_argument("--out", required=True, help="run directory (run the command again to continue it)")
    p.add_argument(
        "--budget",
        default=None,
        help="wall-clock budget of the phases (training and verification), e.g. 30m; checked before each "
        "phase: none starts once it is spent, while the phase under way and the final verification finish",
    )
    for flag, field, kind, text in SETTINGS_OPTIONS:
        p.add_argument(flag, type=kind, default=None, help=f"{text} (default: {default(TrainUntilSettings, field)})")
    # a new run's recipe: every reach train option but the stop rules (a resumed run keeps its own)
    add_training_options(p, skip=STOP_RULES)
    p.set_defaults(func=run)


def _check_continued(out: str, chosen: dict[str, Any]) -> None:
    """A run directory that holds a run continues it under its stored configuration: a training option
    that differs from it is refused, naming it, rather than ignored (each phase resumes the run with
    its own steps and nothing else)."""
    if (Path(out) / "config.json").exists():
        refuse_changes(out, chosen, frozenset(), "train-until continues", "give another --out")


def run(args: argparse.Namespace) -> int:
    from studies.train_until import TrainUntilSettings, train_until  # lazy: keeps `import reach_cli` light

    chosen = {field: getattr(args, field) for _, field, _, _ in SETTINGS_OPTIONS}
    if args.budget is not None:
        chosen["budget_s"] = parse_duration(args.budget)
    settings = TrainUntilSettings(**{k: v for k, v in chosen.items() if v is not None})
    chosen_config = training_fields(args)
    # steps: a stop rule for validation's sake; each phase sets its own (studies.train_until)
    config = TrainConfig(**chosen_config, steps=settings.phase_steps).validate()
    check_output_dir(args.out, "--out")
    _check_continued(args.out, chosen_config)
    record = train_until(config, args.out, settings, progress=True)
    final = record["final"]["verification"]
    print(
        f"{len(record['phases'])} phases, stopped at the {record['stopped']}; final verification "
        f"(seed {record['final']['seed']}, {final['samples']} fresh states): eps {final['eps']}, "
        f"holds: {record['final']['holds']}; record: {args.out}/phases.json"
    )
    return 0
