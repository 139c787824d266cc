"""Air3D accuracy against the grid ground truth as a function of training wall time.

Run: ``python benchmarks/accuracy_vs_time.py --out runs/air3d-default [-- extra reach train options]``

It solves the 101^3 ground truth to t = 1.0 (cached in ``--gt``), trains with
``reach train --system air3d --budget BUDGET --groundtruth GT --eval-every 60 ...`` (evaluation time
is not counted as training time), then prints the evaluations as a markdown table and draws
``OUT/accuracy_vs_time.png``. Metrics: value MSE and IoU of {V <= 0} at t = 1.0 over all 101^3 grid
nodes ("volume") and over the x3 = 1.5863 node slice ("slice").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from reach_cli import main as reach_main


def table(rows: list[dict]) -> str:
    lines = [
        "| step | train s | loss | IoU volume | MSE volume | IoU slice | MSE slice | steps/s |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['step']} | {r['wall']:.0f} | {r['loss']:.4f} | {r['iou_volume']:.3f} | {r['mse_volume']:.2e} | "
            f"{r['iou_slice']:.3f} | {r['mse_slice']:.2e} | {r['steps_per_s']:.1f} |"
        )
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 3.2), dpi=100)
    FigureCanvasAgg(fig)
    wall = [r["wall"] for r in rows]
    ax = fig.add_subplot(1, 2, 1)
    ax.plot(wall, [r["iou_volume"] for r in rows], "o-", label="volume")
    ax.plot(wall, [r["iou_slice"] for r in rows], "s-", label="slice x3=1.5863")
    ax.axhline(0.96, color="grey", linestyle="--", linewidth=0.8, label="goal 0.96")
    ax.set_xlabel("training wall time (s)")
    ax.set_ylabel("IoU of BRT at t = 1.0")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 2, 2)
    ax.semilogy(wall, [r["mse_volume"] for r in rows], "o-", label="volume")
    ax.semilogy(wall, [r["mse_slice"] for r in rows], "s-", label="slice")
    ax.axhline(1.8e-4, color="grey", linestyle="--", linewidth=0.8, label="goal 1.8e-4")
    ax.set_xlabel("training wall time (s)")
    ax.set_ylabel("value MSE at t = 1.0")
    ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)


def score_deepreach(path: Path, gt: Path) -> str:
    """The volume and slice metrics of an imported DeepReach Air3D model at t = 1.0, as a table row."""
    from groundtruth import GridSolution
    from reach.systems import make_system
    from training import NeuralValueFunction, load_deepreach
    from training.accuracy import ReferenceEvaluator

    network = load_deepreach(path, make_system("air3d"), "ssssl")
    m = ReferenceEvaluator(GridSolution.load(gt, outside="clamp"), 1.0)(NeuralValueFunction(network))
    return (
        f"\nDeepReach checkpoint {path.name}: IoU volume {m['iou_volume']:.4f}, MSE volume {m['mse_volume']:.3e}, "
        f"IoU slice {m['iou_slice']:.4f}, MSE slice {m['mse_slice']:.3e}\n"
    )


def main() -> int:
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="run directory")
    parser.add_argument("--budget", default="10m")
    parser.add_argument("--gt", default="runs/air3d_gt_101_t1.npz", help="ground-truth cache")
    parser.add_argument(
        "--also-deepreach",
        default=None,
        metavar="PTH",
        help="also score this DeepReach Air3D checkpoint (ssssl) with the same evaluator, as a yardstick",
    )
    args = parser.parse_args(argv)
    gt = Path(args.gt)
    if not gt.exists():
        code = reach_main(["groundtruth", "air3d", "--grid", "101", "--horizon", "1.0", "--out", str(gt)])
        if code:
            return code
    if args.also_deepreach:
        print(score_deepreach(Path(args.also_deepreach), gt))
    code = reach_main(
        [
            "train",
            "--system",
            "air3d",
            "--budget",
            args.budget,
            "--groundtruth",
            str(gt),
            "--eval-every",
            "60",
            "--log-every",
            "50",
            "--out",
            args.out,
            *extra,
        ]
    )
    if code:
        return code
    rows = [json.loads(line) for line in (Path(args.out) / "metrics.jsonl").read_text().splitlines()]
    rows = [r for r in rows if "iou_volume" in r]
    print(f"\nreach train --system air3d --budget {args.budget} {' '.join(extra)}\n")
    print(table(rows))
    plot(rows, Path(args.out) / "accuracy_vs_time.png", f"Air3D, reach train {' '.join(extra) or '(defaults)'}")
    print(f"\nwrote {Path(args.out) / 'accuracy_vs_time.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
