"""Add or refresh a shipped value network (package data in ``training/pretrained``), for maintainers.

Two steps, each rerunnable:

1. ``export`` copies a finished training run's network (no optimizer state) to
   ``training/pretrained/NAME.pt`` and writes its model card with how it was trained::

       python benchmarks/make_pretrained.py export runs/air3d-10m --name air3d --env-ids Air3D-v0 \\
           --summary "..." --command "reach train --system air3d --budget 10m --seed 0 --out runs/air3d-10m" \\
           --commit cd6e1f2 --hardware "2 CPU cores (shared VM), torch 2.13.0+cpu"

2. ``evaluate`` runs ``reach evaluate`` on ``pretrained:NAME`` (the shipped file, so the card
   scores exactly what ships) and records the command, the sample sizes and the metrics::

       python benchmarks/make_pretrained.py evaluate air3d --samples 100000 --scenario-samples 100000 \\
           --ground-truth runs/air3d_gt.npz

   A grid ships the same way (``export-grid``): a grid solution, resampled to a compact grid,
   becomes ``NAME.npz`` with a card of format ``grid``::

       python benchmarks/make_pretrained.py export-grid runs/pair_gt.npz --name relativepair --resample 51 \
           --summary "..." --command "reach groundtruth relativepair --grid 101 --out runs/pair_gt.npz" \
           --commit 0abc123 --hardware "2 CPU cores (shared VM), torch 2.13.0+cpu"

   and ``filter-source multivehicle9d "cap:pretrained:multivehicle9d,pretrained:relativepair"`` sets
   what the filters of a card's env ids load instead of the bare model.

3. ``record`` adds a ``reach evaluate`` run of the shipped file used another way (capped by the
   pairwise union, rolled out under the greedy policy, ...) to the card's ``also_evaluated``, from
   the JSON that run wrote (its settings and row), with the command that made it::

       python benchmarks/make_pretrained.py record multivehicle9d cap-greedy.json \
           --label "capped by the pairwise union" --command "reach evaluate ..." --commit 4e724e9 \
           --hardware "2 CPU cores (shared VM), torch 2.13.0+cpu"

4. ``adopt`` takes the card's main evaluation from a ``reach evaluate`` run of the same network
   scored elsewhere (its run directory on a GPU, where the card's 1M fresh states take a minute
   instead of hours), from that run's JSON, once the evaluated checkpoint is shown to hold the
   shipped network parameter for parameter::

       python benchmarks/make_pretrained.py adopt multivehicle15d eval.json --checkpoint runs/w256 \
           --command "reach evaluate runs/w256 ... --device cuda" --hardware "one NVIDIA H200 ..."

The test suite (``tests/test_pretrained.py``) reloads every shipped model and checks its card's
rates on a fresh small sample.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import shlex
import sys
import tempfile
from pathlib import Path
from typing import Any

import torch

from reach.atomic import atomic_path
from reach.validation import device_arg, positive_int_arg
from training import pretrained
from training.checkpoint import ARCHITECTURE_KEYS, network_from_payload, read_checkpoint, save_checkpoint

#: the ``reach evaluate`` columns a card keeps
CARD_COLUMNS = (
    "samples",
    "violation_rate",
    "false_safe_rate",
    "false_unsafe_rate",
    "false_reachable_rate",
    "false_unreachable_rate",
    "failure_rate",
    "collision_rate",
    "collision_ci_low",
    "collision_ci_high",
    "delta",
    "eps",
    "scenario_states",
    "scenario_failures",
    "scenario_volume",
    "robust_level",
    "robust_eps",
    "robust_failures",
    "robust_scenario_volume",
    "iou_volume",
    "mse_volume",
    "iou_slice",
    "mse_slice",
    "containment_miss_rate",
    "union_fraction",
)


def write_card(card: pretrained.ModelCard) -> None:
    path = pretrained.DIRECTORY / f"{card.name}{pretrained.CARD_SUFFIX}"
    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        json.dump(card.to_dict(), fh, indent=2)
        fh.write("\n")


def export(args: argparse.Namespace) -> int:
    from safety.value_loading import resolve_checkpoint

    source = resolve_checkpoint(args.run)
    payload = read_checkpoint(source)
    network = network_from_payload(source, payload)
    meta = payload["metadata"]
    keep = {k: v for k, v in meta.items() if k not in (*ARCHITECTURE_KEYS, "format", "integrity")}
    target = pretrained.DIRECTORY / f"{args.name}.pt"
    save_checkpoint(target, network, metadata=keep)
    config = meta.get("config", {})
    card = pretrained.ModelCard(
        name=args.name,
        system=network.system.reference(),
        env_ids=tuple(e for e in args.env_ids.split(",") if e),
        summary=args.summary,
        training={
            "command": args.command,
            "commit": args.commit,
            "wall_time_s": meta.get("wall_time_s"),
            "steps": meta.get("steps"),
            "hardware": args.hardware,
            "layout": meta["layout"],
            "width": meta["width"],
            "points": config.get("points"),
            "seed": meta.get("seed"),
            "versions": meta.get("versions"),
        },
        evaluation={},
        sha256=pretrained.file_sha256(target),
    )
    write_card(card)
    print(f"wrote {target} ({target.stat().st_size / 1024:.0f} KB) and its card; now run: evaluate {args.name}")
    return 0


def export_grid(args: argparse.Namespace) -> int:
    from groundtruth.solution import GridSolution

    solution = GridSolution.load(args.grid)
    compact = solution.resampled(args.resample) if args.resample else solution
    target = pretrained.DIRECTORY / f"{args.name}.npz"
    compact.save(target)
    card = pretrained.ModelCard(
        name=args.name,
        system=compact.system.reference(),
        env_ids=tuple(e for e in args.env_ids.split(",") if e),
        summary=args.summary,
        training={
            "command": args.command,
            "commit": args.commit,
            "hardware": args.hardware,
            "layout": "grid",
            "grid": list(compact.grid.shape),
            "solved_on": list(solution.grid.shape),
            "times": compact.times.tolist(),
            "versions": solution.metadata.get("versions"),
        },
        evaluation={},
        sha256=pretrained.file_sha256(target),
        format="grid",
    )
    write_card(card)
    print(f"wrote {target} ({target.stat().st_size / 1024:.0f} KB) and its card; now run: evaluate {args.name}")
    return 0


def filter_source(args: argparse.Namespace) -> int:
    from safety.value_loading import load_value_function, member_sources

    card = pretrained.card(args.name)
    if args.source and pretrained.PREFIX + args.name not in member_sources(args.source):
        raise SystemExit(f"filter source {args.source!r} does not use {pretrained.PREFIX}{args.name}")
    if args.source:
        load_value_function(args.source, system=card.system)  # refuses what cannot load, before writing
    write_card(dataclasses.replace(card, filter_source=args.source))
    print(f"{args.name}: filters of {', '.join(card.env_ids) or 'no env'} load {args.source or 'the model itself'}")
    return 0


def evaluate(args: argparse.Namespace) -> int:
    from safety.verification.verify import VerifySettings
    from studies.batch_verification import SourceLoading, evaluate_many

    card = pretrained.card(args.name)
    source = pretrained.PREFIX + args.name
    settings = VerifySettings(
        samples=args.samples,
        scenario_samples=args.scenario_samples,
        robust_samples=args.robust_samples,
        seed=args.seed,
        **({} if args.chunk_size is None else {"chunk_size": args.chunk_size}),
    )
    command = ["reach", "evaluate", source, "--samples", str(args.samples)]
    command += ["--scenario-samples", str(args.scenario_samples), "--seed", str(args.seed)]
    if args.robust_samples is not None:
        command += ["--robust-samples", str(args.robust_samples)]
    if args.chunk_size is not None:
        command += ["--chunk-size", str(args.chunk_size)]
    if args.ground_truth:
        command += ["--ground-truth", args.ground_truth]
    if args.pairwise:
        command += ["--pairwise", args.pairwise]
    if args.device != "cpu":
        command += ["--device", args.device]
    with contextlib.ExitStack() as stack:
        # --out keeps the results (and, until the row is in, the rollout store): a run stopped
        # part-way resumes from its finished blocks when started again with the same --out
        out = Path(args.out) if args.out else Path(stack.enter_context(tempfile.TemporaryDirectory())) / "card.csv"
        rows = evaluate_many(
            [source],
            out,
            settings,
            loading=SourceLoading(system=card.system),
            ground_truth=args.ground_truth,
            pairwise=args.pairwise,
            device=args.device,
        )
    row = rows[0]
    if row.get("error"):
        print(f"evaluation failed: {row['error']}", file=sys.stderr)
        return 1
    metrics = card_metrics(row)
    evaluation = {
        "command": " ".join(shlex.quote(c) for c in command) + " --out results.csv",
        "samples": args.samples,
        "scenario_samples": args.scenario_samples,
        "robust_samples": args.robust_samples,
        "seed": args.seed,
        "hardware": args.hardware,
        "wall_time_s": row.get("wall_time"),
        "metrics": metrics,
    }
    write_card(dataclasses.replace(card, evaluation=evaluation))
    print(pretrained.card(args.name).describe())
    return 0


def card_metrics(row: dict) -> dict:
    """The :data:`CARD_COLUMNS` of a ``reach evaluate`` row that hold a number (not None or NaN)."""
    return {k: row[k] for k in CARD_COLUMNS if row.get(k) is not None and row.get(k) == row.get(k)}


def record(args: argparse.Namespace) -> int:
    card = pretrained.card(args.name)
    settings, rows = _evaluation_json(args.results)
    from safety.value_loading import member_sources

    shipped = pretrained.PREFIX + args.name
    rows = [r for r in rows if shipped in member_sources(str(r.get("source", "")))]
    if args.source is not None:
        rows = [r for r in rows if r.get("source") == args.source]
    if len(rows) != 1 or rows[0].get("error"):
        found = [r.get("source") for r in rows]
        raise SystemExit(f"{args.results}: expected one scored row of {shipped} (--source picks one), found {found}")
    row = rows[0]
    entry = {
        "label": args.label,
        "source": row["source"],
        "kind": row.get("kind"),
        "policy": settings.get("policy", "gradient"),
        **evaluation_entry(settings, row, args.command, args.hardware, commit=args.commit),
    }
    others = [e for e in card.also_evaluated if e.get("label") != args.label]
    write_card(dataclasses.replace(card, also_evaluated=(*others, entry)))
    print(pretrained.card(args.name).describe())
    return 0


def evaluation_entry(
    settings: dict, row: dict, command: str, hardware: str, commit: str | None = None
) -> dict[str, Any]:
    """What a card keeps of one ``reach evaluate`` row (its JSON's ``settings`` and the row): the
    command (and the commit, where given), sample sizes, seed, hardware, wall time and metrics."""
    return {
        "command": command,
        **({} if commit is None else {"commit": commit}),
        "samples": settings["samples"],
        "scenario_samples": settings.get("scenario_samples"),
        "robust_samples": settings.get("robust_samples"),
        "seed": settings["seed"],
        "hardware": hardware,
        "wall_time_s": row.get("wall_time"),
        "metrics": card_metrics(row),
    }


def _evaluation_json(path: str) -> tuple[dict, list[dict]]:
    """The settings and rows of a ``reach evaluate`` JSON; anything else stops in one line."""
    try:
        data = json.loads(Path(path).read_text())
        return data["settings"], data["results"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise SystemExit(f"{path}: not the JSON of a reach evaluate run ({type(err).__name__}: {err})") from err


def same_network(a: Any, b: Any) -> bool:
    """Whether two value networks compute the same function: the same system (with its parameters),
    layout, parameterisation, frequency and input encoding, and every parameter equal, bit for bit."""
    described = ("layout", "width", "parameterisation", "w0", "encoding")
    if a.system.reference() != b.system.reference() or any(getattr(a, k) != getattr(b, k) for k in described):
        return False
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(
        sa[k].shape == sb[k].shape and sa[k].dtype == sb[k].dtype and torch.equal(sa[k], sb[k]) for k in sa
    )


#: the settings of the cards' protocol that an adopted evaluation must share (the sample sizes, seed
#: and batch size may differ; they are recorded)
PROTOCOL = ("beta", "dt", "integrator", "horizon", "matmul_precision", "target_eps", "policy", "control_period")


def check_protocol(settings: dict, where: str) -> None:
    """Refuse, naming the setting, an evaluation whose rollouts or bounds differ from the cards' protocol
    (:class:`~safety.verification.verify.VerifySettings`' defaults), so an adopted row means the same
    as one ``evaluate`` writes."""
    from safety.verification.verify import VerifySettings

    protocol = dataclasses.asdict(VerifySettings())
    for key in PROTOCOL:
        if settings.get(key, protocol[key]) != protocol[key]:
            raise SystemExit(f"{where}: {key} is {settings[key]!r}; the cards' protocol has {protocol[key]!r}")


def adopt(args: argparse.Namespace) -> int:
    from safety.value_loading import resolve_checkpoint

    card = pretrained.card(args.name)
    settings, rows = _evaluation_json(args.results)
    rows = [r for r in rows if args.source is None or r.get("source") == args.source]
    if len(rows) != 1 or rows[0].get("error"):
        found = [(r.get("source"), r.get("error")) for r in rows]
        raise SystemExit(f"{args.results}: expected one scored row (--source picks one), found {found}")
    row = rows[0]
    check_protocol(settings, args.results)
    source = resolve_checkpoint(args.checkpoint)
    evaluated = network_from_payload(source, read_checkpoint(source))
    target = pretrained.DIRECTORY / f"{args.name}.pt"
    shipped = network_from_payload(target, read_checkpoint(target))
    if not same_network(evaluated, shipped):
        raise SystemExit(f"{args.checkpoint}: its network is not the shipped {args.name}'s; score the shipped file")
    fingerprint = row.get("fingerprint") or {}
    if fingerprint.get("size") not in (None, source.stat().st_size):
        raise SystemExit(
            f"{args.results}: it scored a file of {fingerprint['size']} bytes, {source} has {source.stat().st_size}"
        )
    evaluation = evaluation_entry(settings, row, args.command, args.hardware)
    write_card(dataclasses.replace(card, evaluation=evaluation))
    print(pretrained.card(args.name).describe())
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="step", required=True)
    e = sub.add_parser("export", help="copy a run's network into the package and write its card")
    e.add_argument("run", help="training run directory or checkpoint")
    e.add_argument("--name", required=True)
    e.add_argument("--env-ids", default="", help="comma-separated Gymnasium ids this model filters by default")
    e.add_argument("--summary", required=True)
    e.add_argument("--command", required=True, help="the command that trained it")
    e.add_argument("--commit", required=True)
    e.add_argument("--hardware", required=True)
    e.set_defaults(func=export)
    g = sub.add_parser("export-grid", help="copy a grid solution (resampled) into the package and write its card")
    g.add_argument("grid", help="a grid solution .npz (reach groundtruth)")
    g.add_argument("--name", required=True)
    g.add_argument("--resample", type=positive_int_arg, default=None, help="nodes per dimension of the shipped grid")
    g.add_argument("--env-ids", default="", help="comma-separated Gymnasium ids this grid filters by default")
    g.add_argument("--summary", required=True)
    g.add_argument("--command", required=True, help="the command that solved it")
    g.add_argument("--commit", required=True)
    g.add_argument("--hardware", required=True)
    g.set_defaults(func=export_grid)
    f = sub.add_parser("filter-source", help="what the filters of a card's env ids load (empty: the model)")
    f.add_argument("name")
    f.add_argument("source", help='e.g. "cap:pretrained:multivehicle9d,pretrained:relativepair"; "" resets')
    f.set_defaults(func=filter_source)
    v = sub.add_parser("evaluate", help="score the shipped file with reach evaluate and record it in the card")
    v.add_argument("name")
    v.add_argument("--samples", type=int, default=100_000)
    v.add_argument("--scenario-samples", type=int, default=100_000)
    v.add_argument("--robust-samples", type=int, default=None)
    v.add_argument("--seed", type=int, default=0)
    v.add_argument("--chunk-size", type=positive_int_arg, default=None, help="states per rollout batch (memory only)")
    v.add_argument("--ground-truth", default=None)
    v.add_argument("--pairwise", default=None)
    v.add_argument("--device", type=device_arg, default="cpu", help="cpu or cuda: where the rollouts run")
    v.add_argument("--hardware", default="2 CPU cores (shared VM), torch 2.13.0+cpu")
    v.add_argument("--out", default=None, help="keep the results here; a stopped run resumes from its rollout store")
    v.set_defaults(func=evaluate)
    r = sub.add_parser("record", help="add a reach evaluate run of the shipped file (its JSON) to the card")
    r.add_argument("name")
    r.add_argument("results", help="the .json that reach evaluate --out wrote beside its CSV")
    r.add_argument("--label", required=True, help="what this evaluation is, e.g. 'capped by the pairwise union'")
    r.add_argument("--source", default=None, help="which row, where the run scored several sources")
    r.add_argument("--command", required=True, help="the reach evaluate command, as run from the repo root")
    r.add_argument("--commit", required=True)
    r.add_argument("--hardware", required=True)
    r.set_defaults(func=record)
    a = sub.add_parser("adopt", help="the card's evaluation from a reach evaluate run of the same network")
    a.add_argument("name")
    a.add_argument("results", help="the .json that reach evaluate --out wrote beside its CSV")
    a.add_argument("--checkpoint", required=True, help="the run directory or checkpoint that run scored")
    a.add_argument("--source", default=None, help="which row, where the run scored several sources")
    a.add_argument("--command", required=True, help="the reach evaluate command, as it was run")
    a.add_argument("--hardware", required=True)
    a.set_defaults(func=adopt)
    args = parser.parse_args()
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
