"""The CPU recipes of the catalogue's models of 6D and above (issue 42, point 4), as one resumable queue.

Run::

    python benchmarks/catalogue_recipes.py status                 # each recipe's command and progress
    python benchmarks/catalogue_recipes.py measure [--seconds 60]  # the quiet 2-core rate of each system
    python benchmarks/catalogue_recipes.py run [--threads 2]       # train them in turn, resuming any
    python benchmarks/catalogue_recipes.py run --names quadrotor --device cuda   # one recipe, on a GPU

Each recipe trains for two hours of the quiet 2-core rate, given as steps (``minutes x steps per
minute``, the rate ``measure`` printed on a quiet machine), so a run that shares the cores or is
stopped and resumed trains exactly what a quiet, uninterrupted two hours trains: the cosine learning
rate schedule depends on the step count, not on the wall clock. ``run`` works through the queue in
order, in this process (:func:`studies.step_budget_study.train_or_resume`, as the 9D studies
train); a finished run is skipped, an interrupted one resumes (its checkpoint is at most 30 s old),
and a run directory that another process owns stops the queue with the owner's error. Each run's
line in the log is its ``reach train`` command. Each run keeps 24 snapshots of its network, one per 5 quiet minutes
(``RUN/snapshots``), so the accuracy of every model along its training can be scored afterwards
(the dimension study). The N-car fleets train under the union of pairwise BRTs of the 101^3 pair
grid (``--upper-bound runs/pair_gt.npz``, which ``run`` solves first if it is missing, as
``reach groundtruth relativepair --grid 101 --out runs/pair_gt.npz`` does, 20 s), as the shipped 9D
model does.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from reach.threads import thread_policy
from reach.validation import device_arg
from reach_cli.train import train_flags
from studies.step_budget_study import ensure_pairwise, train_or_resume

ROOT = Path(__file__).resolve().parents[1]
#: the CLI of this interpreter's reach (no PATH lookup)
REACH = (sys.executable, "-m", "reach")
OUT = Path("runs/catalogue")
MINUTES = 120
#: network snapshots over each run, one per 5 quiet minutes: the dimension study scores them afterwards
SNAPSHOTS = 24


@dataclass(frozen=True)
class Recipe:
    """One model's training: the system, its quiet 2-core rate, and its settings beyond the defaults
    (:class:`~training.TrainConfig` fields, as ``reach train`` takes them: ``upper_bound`` is
    ``--upper-bound``)."""

    name: str
    system: str
    steps_per_minute: int  # measured by ``measure`` on a quiet machine (see ``rate_from``)
    rate_from: str
    settings: tuple[tuple[str, Any], ...] = ()

    @property
    def steps(self) -> int:
        return MINUTES * self.steps_per_minute

    @property
    def out(self) -> Path:
        return OUT / self.name

    def fields(self) -> dict[str, Any]:
        """The run's :class:`~training.TrainConfig` fields besides steps and seed."""
        return {"system": self.system, "snapshots": SNAPSHOTS, **dict(self.settings)}

    def command(self, threads: int) -> list[str]:
        """The ``reach train`` command line of this recipe (what ``run`` trains, in this process)."""
        command = ["reach", "--threads", str(threads), "train", *train_flags(self.fields())]
        command += ["--steps", str(self.steps), "--seed", "0"]
        return [*command, "--out", str(self.out)]


PAIR_GRID = Path("runs/pair_gt.npz")
UNION = (("upper_bound", str(PAIR_GRID)),)
MEASURED = "2026-11-26, `measure --seconds 60`, quiet (other runs paused): "
#: the queue, in the order ``run`` trains it
RECIPES = (
    Recipe("multivehicle12d", "multivehicle12d", 660, "2026-11-26, 11.0 steps/s over 70 s, quiet", UNION),
    Recipe("multivehicle15d", "multivehicle15d", 630, MEASURED + "10.5 steps/s", UNION),
    # the shipped 9D model's recipe (its card's rate), again with snapshots: the dimension study's 3 cars
    Recipe("multivehicle9d", "multivehicle9d", 770, "the shipped 9D card: 92,400 steps in 120 quiet minutes", UNION),
    Recipe("narrowpassage", "narrowpassage", 1241, MEASURED + "20.7 steps/s"),
    Recipe("quadrotor", "quadrotor", 1278, MEASURED + "21.3 steps/s"),
    Recipe("reachavoidrocketlanding", "reachavoidrocketlanding", 785, MEASURED + "13.1 steps/s"),
)


def _progress(recipe: Recipe) -> tuple[int, float]:
    """Steps and wall seconds of the run's last checkpoint (0, 0 before the first)."""
    meta = ROOT / recipe.out / "checkpoint.json"
    if not meta.is_file():
        return 0, 0.0
    data = json.loads(meta.read_text())
    return int(data.get("steps", 0)), float(data.get("wall_time_s") or 0.0)


def status(args: argparse.Namespace) -> int:
    for recipe in RECIPES:
        steps, wall = _progress(recipe)
        target = recipe.steps or "?"
        print(f"{recipe.name:<26} {steps:>6} / {target} steps, {wall / 60:.0f} min so far")
        if recipe.steps_per_minute:
            print(f"    {shlex.join(recipe.command(args.threads))}   # {recipe.rate_from}")
        else:
            print("    (no measured rate yet: run `measure` on a quiet machine)")
    return 0


def measure(args: argparse.Namespace) -> int:
    """Each system's steps per minute over ``--seconds`` of training, one system at a time."""
    ensure_pairwise(ROOT / PAIR_GRID)
    for recipe in RECIPES:
        if args.names and recipe.name not in args.names.split(","):
            continue
        out = ROOT / "runs" / "catalogue-rate" / recipe.name
        command = [*REACH, *recipe.command(args.threads)[1:-2], "--out", str(out), "--log-every", "25"]
        command[command.index("--steps") + 1] = "1000000"
        subprocess.run(["rm", "-rf", str(out)], check=True)
        start = time.perf_counter()
        with contextlib.suppress(subprocess.TimeoutExpired):
            subprocess.run(command, timeout=args.seconds, capture_output=True, cwd=ROOT)
        rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines() if line.strip()]
        steps = [r for r in rows if "steps_per_s" in r]
        rate = sum(r["steps_per_s"] for r in steps[len(steps) // 2 :]) / max(1, len(steps) - len(steps) // 2)
        print(
            f"{recipe.name:<26} {rate:.2f} steps/s = {60 * rate:.0f} steps/min (second half of "
            f"{time.perf_counter() - start:.0f} s, {args.threads} threads)"
        )
    return 0


def run(args: argparse.Namespace) -> int:
    ensure_pairwise(ROOT / PAIR_GRID)
    names = None if args.names is None else args.names.split(",")
    unknown = sorted(set(names or ()) - {recipe.name for recipe in RECIPES})
    if unknown:
        raise SystemExit(f"--names: no recipe {', '.join(map(repr, unknown))} (recipes: {[r.name for r in RECIPES]})")
    with thread_policy(args.threads):  # as `reach --threads`: the runs train with this many threads
        return _train_queue(args.threads, names, args.device)


def _train_queue(threads: int, names: list[str] | None, device: str) -> int:
    for recipe in RECIPES:
        if names is not None and recipe.name not in names:
            continue
        if not recipe.steps_per_minute:
            print(f"{recipe.name}: no measured rate; the queue stops here (run `measure`)")
            return 1
        steps, _ = _progress(recipe)
        if steps >= recipe.steps:
            print(f"{recipe.name}: done ({steps} steps)")
            continue
        run_dir = ROOT / recipe.out
        if (run_dir / "config.json").is_file():
            shown = ["reach", "--threads", str(threads), "train", "--resume", str(recipe.out)]
            shown += ["--steps", str(recipe.steps)]
        else:
            shown = recipe.command(threads)
        if device != "cpu":
            shown[shown.index("train") + 1 : shown.index("train") + 1] = ["--device", device]
        print(f"{recipe.name}: {shlex.join(shown)}", flush=True)
        fields = {k: str(ROOT / v) if k == "upper_bound" else v for k, v in recipe.fields().items()}
        if train_or_resume(run_dir, recipe.steps, 0, fields, device=device):
            return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="stage", required=True)
    for name, func in (("status", status), ("measure", measure), ("run", run)):
        s = sub.add_parser(name)
        s.add_argument("--threads", type=int, default=2)
        if name in ("measure", "run"):
            s.add_argument("--names", default=None, help="comma-separated recipes (default: all)")
        if name == "measure":
            s.add_argument("--seconds", type=float, default=60.0)
        if name == "run":
            # the recipe is its step count: a GPU trains the same steps (issue 42, point 6), and a run
            # may move between devices when it resumes
            s.add_argument("--device", type=device_arg, default="cpu", help="cpu or cuda (default: cpu)")
        s.set_defaults(func=func)
    args = p.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
