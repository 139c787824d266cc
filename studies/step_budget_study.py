"""A resumable train/score study of named 9D training recipes at fixed step budgets and seeds.

What: the studies of ``benchmarks/nine_d_*.py`` (accuracy against training time, the ablation of
recipe changes, the layouts at equal wall time) each train a set of runs of the three-car system
(:data:`SYSTEM`), one per (name, budget, seed), into ``OUT/runs/<name>-<M>m-seed<S>``, then score
every finished run with the same rollout verification into one merged table ``OUT/results.csv``
(``.json``, ``.md``), beside the union of pairwise BRTs. :mod:`studies.step_budget_report` reads
that table back and prints and draws it. The scripts keep only their command lines and their rows.

Why one module: the three studies must train and score their runs alike (a row of one is compared
with a row of another, and the ablation's baseline *is* the time study's run), so the stages live
here once, written against the library (:class:`training.Trainer`,
:func:`studies.batch_verification.evaluate_many`, :func:`groundtruth.solve`), not the command line.

Why step budgets: a budget of M minutes is trained as ``M x steps_per_minute`` steps, a fixed
reference rate (:data:`QUIET_STEPS_PER_MINUTE`), not as wall-clock time, so a run trains the same
steps, with the same schedule, whatever else shares its cores. Every stage skips what is done: a run
with a checkpoint is resumed (on any device: the step count, not the machine, fixes what it trains),
only finished runs are scored, and the table
merges rows (:func:`~studies.batch_verification.evaluate_many`), so a study may be stopped at any
time and split across sessions or machines.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from groundtruth import Grid, SolverSettings, solve
from groundtruth.solver import check_memory, default_output_times
from reach.exit_codes import EXIT_PARTIAL
from reach.systems import make_system
from reach.threads import thread_policy
from reach.validation import check_output_path, csv_floats, csv_items, device_arg, positive_int_arg
from safety.verification.verify import VerifySettings
from studies.batch_verification import evaluate_many, markdown_table, report_failures
from studies.step_budget_report import RESULTS
from training import TrainConfig, Trainer, TrainingDivergedError

#: the system every run trains on: three cars (``reach train --system multivehicle9d``)
SYSTEM = "multivehicle9d"
#: the reference rate at which minutes are converted to steps: the 9D default network's (ssssl, 4x128,
#: 8192 points, compiled) on the project's 2-core CPU, in the run that opened issue 18 (measured:
#: docs/results/studies.md)
QUIET_STEPS_PER_MINUTE = 923.0
#: the union of pairwise BRTs (``reach groundtruth relativepair --grid 101``), solved once where missing
DEFAULT_PAIRWISE = "runs/pair_gt.npz"

#: stands for the pairwise grid's path in :data:`CHANGES` (the study's ``--pairwise``)
PAIRWISE = "{pairwise}"
#: the changes to the default recipe, each as the :class:`~training.TrainConfig` fields that make it
CHANGES: dict[str, dict[str, Any]] = {
    "baseline": {},
    # a known upper bound of the true value: V may not exceed the union of pairwise values
    "upper-bound": {"upper_bound": PAIRWISE},
    # a known lower bound: V may not sit below what the network's own policy achieves (rollout labels)
    "lower-bound": {"lower_bound": "policy"},
    # DeepReach-MPC-style labels: the best of sampled control sequences, bootstrapped by the network
    "mpc-labels": {"lower_bound": "mpc"},
    # both bounds: the union from above, the network's own policy from below
    "both-bounds": {"upper_bound": PAIRWISE, "lower_bound": "policy"},
    # a quarter of each step's points where the network's own |V| is smallest (of 4x as many draws)
    "zero-level": {"zero_level_fraction": 0.25},
    # the two terms that pushed towards soundness, without the labels that pulled the other way
    "upper-zero-level": {"upper_bound": PAIRWISE, "zero_level_fraction": 0.25},
    # issue 18's candidate recipe: both bounds and the zero-level points together. Trained for 2 hours
    # of its own rate (``--minutes 120 --steps-per-minute 433``; measured: docs/results/training.md)
    "recipe": {"upper_bound": PAIRWISE, "lower_bound": "policy", "zero_level_fraction": 0.25},
}


def change_settings(change: str, pairwise: str) -> dict[str, Any]:
    """The training fields of ``change`` (a key of :data:`CHANGES`), the pairwise grid at ``pairwise``."""
    return {key: pairwise if value == PAIRWISE else value for key, value in CHANGES[change].items()}


def run_path(out: Path, name: str, minutes: float, seed: int, suffix: str = "") -> Path:
    """The folder of a study's run: ``OUT/runs/<name>-<M>m<suffix>-seed<S>`` (its label in the table)."""
    return out / "runs" / f"{name}-{minutes:g}m{suffix}-seed{seed}"


@dataclass(frozen=True)
class PlannedRun:
    """One run of a study: its folder, the steps it trains, its seed and its changes to the defaults."""

    path: Path
    steps: int
    seed: int
    settings: Mapping[str, Any] = field(default_factory=dict)


def train_or_resume(
    run: Path, steps: int, seed: int, settings: Mapping[str, Any] | None = None, device: str = "cpu"
) -> int:
    """Train the 9D defaults (plus ``settings``, :class:`~training.TrainConfig` fields; a ``system``
    among them trains that system instead) for ``steps`` steps into ``run`` on ``device``, or resume
    the run already there (on ``device``: a run may move
    between a CPU and a GPU; the step count, not the machine, fixes what it trains). Returns 0, or
    :data:`EXIT_PARTIAL` where the run diverged (its last good checkpoint is kept)."""
    with thread_policy():  # as `reach train`: the cores other processes leave free, for the whole run
        if any((run / name).exists() for name in ("checkpoint.pt", "config.json")):
            trainer = Trainer.resume(run, steps=steps, device=device)
        else:
            fields = {"system": SYSTEM, **(settings or {})}
            config = TrainConfig(steps=steps, seed=seed, device=device, **fields)
            trainer = Trainer(config, run)  # which validates the configuration first
        try:
            summary = trainer.train()
        except TrainingDivergedError as err:
            print(f"{run}: {err}", file=sys.stderr)
            return EXIT_PARTIAL
    print(f"{summary['run_dir']}: {summary['steps']} steps in {summary['wall_time_s']:.1f} s ({summary['stopped']})")
    return 0


def train_runs(runs: Sequence[PlannedRun], device: str = "cpu") -> int:
    """Train or resume ``runs`` in their order, solving first the pairwise grid any of them trains
    against (a run resumed on a fresh machine needs it as much as a new one). Stops at the first run
    that fails and returns its status (0: all trained)."""
    for grid in dict.fromkeys(str(run.settings["upper_bound"]) for run in runs if run.settings.get("upper_bound")):
        ensure_pairwise(Path(grid))
    for run in runs:
        code = train_or_resume(run.path, run.steps, run.seed, run.settings, device)
        if code:
            return code
    return 0


def finished(run: Path) -> bool:
    """Whether ``run`` reached the steps it was started for. A run stopped early (SIGTERM, a time
    limit) has a checkpoint too, and scoring it would put a half-trained network in the table."""
    record = run / "checkpoint.json"
    if not record.exists():
        return False
    meta = json.loads(record.read_text())
    target = meta.get("config", {}).get("steps")
    return target is None or int(meta.get("steps", 0)) >= int(target)


def solve_pairwise(path: Path) -> Path:
    """Solve the union of pairwise BRTs into ``path``: ``relativepair`` on a 101^3 grid, every 0.1 s
    to its horizon (what ``reach groundtruth relativepair --grid 101`` writes)."""
    system = make_system("relativepair")
    times = default_output_times(system.horizon)
    check_memory(Grid.for_system(system, 101).shape, len(times), torch.float32)
    check_output_path(path, "pairwise grid")
    with thread_policy():
        solution = solve(system, 101, times, settings=SolverSettings(dtype=torch.float32))
    saved = solution.save(path)
    shape, steps = "x".join(map(str, solution.grid.shape)), solution.metadata["scheme"]["steps"]
    print(
        f"wrote {saved}: {system.name} on {shape}, {len(times)} times from {times[0]:g} to {times[-1]:g}, "
        f"{steps} steps, {solution.metadata['wall_time_s']:.1f} s"
    )
    return saved


def ensure_pairwise(path: Path) -> None:
    """Solve the pairwise grid into ``path`` unless it is there: the scoring needs it, and so does
    every run trained with ``upper_bound``, also when it resumes on a fresh machine."""
    if not path.exists():
        solve_pairwise(path)


@dataclass(frozen=True)
class Scoring:
    """How a study scores its runs: the same uniform states and fresh scenario states for every
    run, the pairwise union for the containment columns, and where the rollouts run."""

    samples: int = 100_000
    scenario_samples: int = 1_000_000
    pairwise: str = DEFAULT_PAIRWISE
    device: str = "cpu"
    chunk_size: int | None = None  # states per batch (None: the verification's default)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Scoring:
        """The settings :func:`add_run_arguments` parsed."""
        return cls(args.samples, args.scenario_samples, str(args.pairwise), args.device, args.chunk_size)


def score_runs(runs: Iterable[Path], out: Path, scoring: Scoring) -> int:
    """Verify the finished ones of ``runs`` with ``scoring`` (solving the pairwise union first if
    missing) into ``out / results.csv``, merged with the rows already there. Returns 0, 1 where no
    run is finished yet, :data:`EXIT_PARTIAL` where a run could not be scored (its row says why)."""
    ensure_pairwise(Path(scoring.pairwise))
    done = [str(run) for run in runs if finished(run)]
    if not done:
        print("no finished runs yet", file=sys.stderr)
        return 1
    chunk = {} if scoring.chunk_size is None else {"chunk_size": scoring.chunk_size}
    settings = VerifySettings(samples=scoring.samples, scenario_samples=scoring.scenario_samples, **chunk)
    table = out / RESULTS
    with thread_policy():  # as `reach evaluate`: sampling and the pairwise union too, not only the rollouts
        rows = evaluate_many(done, table, settings, pairwise=scoring.pairwise, device=scoring.device)
    print(markdown_table(rows))
    print(f"\nwrote {table.with_suffix('.csv')}, {table.with_suffix('.json')}, {table.with_suffix('.md')}")
    return report_failures(rows, "score", "runs")


def float_list(text: str) -> list[float]:
    """argparse type: comma-separated finite numbers, e.g. budgets in minutes ``10,30,60``
    (:func:`reach.validation.csv_floats`: an empty item is refused)."""
    return csv_floats("value", text)


def int_list(text: str) -> list[int]:
    """argparse type: comma-separated integers, e.g. seeds ``0,1`` (an empty item is refused)."""
    return [int(v) for v in csv_items("value", text)]


def stage_parser(description: str, out: str) -> argparse.ArgumentParser:
    """A study's command line: the stage (``train``, ``score``, ``report``) and ``--out`` (default ``out``)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("stage", choices=["train", "score", "report"])
    parser.add_argument("--out", type=Path, default=Path(out))
    return parser


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """The seeds, the step rate and the scoring settings: one source for every study, so that all
    of them train and score their runs the same way."""
    parser.add_argument("--seeds", type=int_list, default=[0, 1])
    parser.add_argument("--steps-per-minute", type=float, default=QUIET_STEPS_PER_MINUTE)
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--scenario-samples", type=int, default=1_000_000)
    parser.add_argument("--pairwise", default=DEFAULT_PAIRWISE)
    parser.add_argument("--device", type=device_arg, default="cpu", help="train and score on this device (cpu or cuda)")
    parser.add_argument(
        "--chunk-size",
        type=positive_int_arg,
        default=None,
        help="states per batch when scoring (reach evaluate's default; on a GPU 262144 avoids being launch-bound)",
    )
