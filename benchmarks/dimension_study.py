"""Accuracy against dimension (issue 42, point 5): the N-car family at 3, 4 and 5 cars (9D, 12D, 15D).

Run (resumable: scored snapshots are kept and skipped)::

    python benchmarks/catalogue_recipes.py run                     # trains the fleets, 24 snapshots each
    python benchmarks/dimension_study.py score [--samples 20000]   # rolls out every snapshot
    python benchmarks/dimension_study.py report                    # the table and docs/dimension_study.png

Every fleet trains by the same recipe (:mod:`catalogue_recipes`: two hours of its quiet 2-core
rate, under the union of pairwise BRTs), and keeps a snapshot of its network every 5 quiet minutes.
``score`` verifies each snapshot as ``reach evaluate`` does (``--samples`` uniform states, the
gradient policy, no scenario bound), so its false-safe rate is a statistical estimate with a Wilson
interval; ``report`` gives, per fleet, the first quiet minute from which the false-safe rate stays at
most 0.1 % (a young network calls nearly every state unsafe, so the first crossing would say
nothing), the rates at two hours, and the card-protocol volumes of the final model: a ``reach
evaluate`` of the run directory given by ``--scored``, else the shipped card trained into it.
Minutes are quiet minutes (snapshot index x 5), not the wall time of a shared machine.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from reach.validation import device_arg

ROOT = Path(__file__).resolve().parents[1]
#: (cars, registered system, run directory of its recipe)
FLEETS = (
    (3, "multivehicle9d", Path("runs/catalogue/multivehicle9d")),
    (4, "multivehicle12d", Path("runs/catalogue/multivehicle12d")),
    (5, "multivehicle15d", Path("runs/catalogue/multivehicle15d")),
)
OUT = Path("runs/studies/dimension")
GOAL = 1e-3  # the false-safe rate whose first crossing the study times
MINUTES_PER_SNAPSHOT = 5.0


def _snapshots(run: Path) -> list[Path]:
    return sorted((ROOT / run / "snapshots").glob("*.pt"))


def score(args: argparse.Namespace) -> int:
    from safety.verification.verify import VerifySettings
    from studies.batch_verification import SourceLoading, evaluate_many

    settings = VerifySettings(samples=args.samples, scenario_samples=0, robust_samples=0, seed=args.seed)
    for cars, system, run in FLEETS:
        if args.fleets and system not in args.fleets.split(","):
            continue
        snapshots = _snapshots(run)
        if not snapshots:
            print(f"{cars} cars: no snapshots in {run} yet")
            continue
        out = ROOT / OUT / f"{system}.csv"
        rows = evaluate_many(
            [str(p) for p in snapshots],
            out,
            settings,
            loading=SourceLoading(system=system),
            pairwise=args.pairwise,
            device=args.device,
        )
        print(f"{cars} cars: {len(rows)} snapshots scored into {out.relative_to(ROOT)}")
    return 0


def _curve(system: str) -> list[tuple[float, float, int, float]]:
    """(quiet minutes, false-safe rate, samples, false-unsafe rate) per scored snapshot, in order."""
    from studies.batch_verification import load_results

    path = ROOT / OUT / f"{system}.csv"
    if not path.with_suffix(".json").is_file():
        return []
    points = []
    for row in load_results(path):
        if row.get("error"):
            continue
        index = int(Path(str(row["source"])).stem)
        minutes = index * MINUTES_PER_SNAPSHOT
        points.append((minutes, float(row["false_safe_rate"]), int(row["samples"]), float(row["false_unsafe_rate"])))
    return sorted(points)


def minutes_to_stay_below(curve: list[tuple[float, float, int, float]], goal: float = GOAL) -> float | None:
    """The first snapshot's minutes from which every later snapshot's false-safe rate is at most
    ``goal`` (None if the last one is above it).

    Not the first crossing: a young network calls nearly every state unsafe, so its false-safe
    rate starts near 0 while it is useless (its false-unsafe rate is tens of percent); the rate
    climbs as the safe set grows and only then settles."""
    first = None
    for minutes, rate, _, _ in curve:
        if rate > goal:
            first = None
        elif first is None:
            first = minutes
    return first


def _final_scores(run: Path, extra: list[str]) -> dict | None:
    """The card-protocol metrics of ``run``'s final model: a ``reach evaluate`` results file among
    ``extra`` whose row scored the run directory, else the shipped card trained into that run."""
    from studies.batch_verification import load_results
    from training import pretrained

    for path in extra:
        for row in load_results(path):
            if str(row.get("source", "")).rstrip("/") == str(run) and not row.get("error"):
                return {"metrics": row, "from": f"`{Path(path).name}`"}
    for name in pretrained.names():
        card = pretrained.card(name)
        if f"--out {run}" in card.training.get("command", "") and card.evaluation:
            return {"metrics": card.evaluation["metrics"], "from": f"card of `pretrained:{name}`"}
    return None


def report(args: argparse.Namespace) -> int:
    from safety.verification.metrics import wilson_interval

    print(
        "| cars | state dim | minutes until false safe stays <= 0.1 % | false safe % at 120 min [95 % CI] "
        "| false unsafe % at 120 min | delta-level vol. (1M) | robust vol. [eps] | final scores from |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---|")
    curves = {}
    for cars, system, run in FLEETS:
        curve = curves[cars] = _curve(system)
        if not curve:
            print(f"| {cars} | {3 * cars} | (not scored) | | | | | |")
            continue
        stays = minutes_to_stay_below(curve)
        _, rate, n, unsafe = curve[-1]
        low, high = wilson_interval(round(rate * n), n)
        final = _final_scores(run, args.scored)
        metrics = {} if final is None else final["metrics"]
        volume = metrics.get("scenario_volume")
        robust, robust_eps = metrics.get("robust_scenario_volume"), metrics.get("robust_eps")
        print(
            f"| {cars} | {3 * cars} | {'not by 120' if stays is None else f'{stays:.0f}'} | "
            f"{100 * rate:.3f} [{100 * low:.3f}, {100 * high:.3f}] | {100 * unsafe:.2f} | "
            f"{'-' if volume is None else f'{volume:.3f}'} | "
            f"{'none found' if robust is None else f'{robust:.3f} [{robust_eps:.2e}]'} | "
            f"{'-' if final is None else final['from']} |"
        )
    if args.plot and any(curves.values()):
        _plot(curves, ROOT / args.plot)
        print(f"wrote {args.plot}")
    return 0


def _plot(curves: dict[int, list[tuple[float, float, int, float]]], path: Path) -> None:
    # lazy: matplotlib only when drawing
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 3.8), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for cars, curve in sorted(curves.items()):
        if curve:
            ax.plot(
                [m for m, _, _, _ in curve],
                [100 * max(r, 1e-5) for _, r, _, _ in curve],
                marker="o",
                label=f"{cars} cars ({3 * cars}D)",
            )
    ax.axhline(100 * GOAL, color="k", lw=0.8, ls="--", label="0.1 %")
    ax.set_yscale("log")
    ax.set_xlabel("training time (quiet 2-core minutes)")
    ax.set_ylabel("false safe % (gradient policy)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="stage", required=True)
    s = sub.add_parser("score")
    s.add_argument("--samples", type=int, default=20_000)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--pairwise", default="runs/pair_gt.npz", help="the pair grid whose union rows are checked against")
    s.add_argument("--fleets", default="", help="comma-separated systems to score (default: all three)")
    s.add_argument("--device", type=device_arg, default="cpu", help="where the rollouts run (cpu, cuda)")
    s.set_defaults(func=score)
    r = sub.add_parser("report")
    r.add_argument(
        "--scored",
        action="append",
        default=[],
        help="a reach evaluate results file of a final run directory (card protocol); else its shipped card",
    )
    r.add_argument("--plot", default="docs/dimension_study.png")
    r.set_defaults(func=report)
    args = p.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
