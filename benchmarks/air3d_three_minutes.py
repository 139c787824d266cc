"""Air3D in three CPU minutes (issue 45, point 4): the fast recipe against the defaults, side by side.

Run on a quiet machine (the budget is wall time)::

    python benchmarks/air3d_three_minutes.py --seeds 0 1 2 --budget 3m --out runs/air3d-3min

For each seed it trains both recipes for the same wall-clock budget, one after the other, with the
same threads (``reach train --system air3d --budget 3m`` for the defaults, the same with
:data:`training.recipes.CPU_3D`'s settings for the fast one), then scores each final network
against the 101^3 grid at t = 1.0 (solved into ``--gt`` if missing): volume IoU of the BRT and value
MSE over all grid nodes, the metrics DeepReach published (IoU 0.957, MSE 1.8e-4; our goal IoU >= 0.96
and MSE <= 1.8e-4). The table gives each run's steps and its training seconds (compilation included,
the trainer's own clock); a finished run is skipped when the command is run again.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from reach_cli import main as reach_main
from reach_cli.train import train_flags
from training.config import parse_duration
from training.recipes import CPU_3D

#: what each row trains besides ``--system air3d --budget B --seed S``
RECIPES = {"defaults": {}, "fast (CPU_3D)": CPU_3D}
GOAL = {"iou_volume": 0.96, "mse_volume": 1.8e-4}


def _score(run: Path, gt: Path) -> dict:
    from groundtruth import GridSolution
    from training import NeuralValueFunction, load_network
    from training.accuracy import ReferenceEvaluator

    evaluator = ReferenceEvaluator(GridSolution.load(gt, outside="clamp"), 1.0)
    return evaluator(NeuralValueFunction(load_network(run / "checkpoint.pt")))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--budget", default="3m")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--gt", default="runs/air3d_gt_101_t1.npz", help="ground-truth cache (101^3, t <= 1.0)")
    parser.add_argument("--out", default="runs/air3d-3min")
    args = parser.parse_args()
    budget = parse_duration(args.budget)
    gt, out = Path(args.gt), Path(args.out)
    if not gt.exists():
        code = reach_main(["--threads", str(args.threads), "groundtruth", "air3d", "--grid", "101", "--horizon", "1.0",
                           "--out", str(gt)])  # fmt: skip
        if code:
            return code
    rows = []
    for seed in args.seeds:
        for label, fields in RECIPES.items():
            run = out / f"{'fast' if fields else 'defaults'}-seed{seed}"
            scored = run / "score.json"
            if not scored.exists():
                if not (run / "checkpoint.pt").exists():
                    command = ["--threads", str(args.threads), "train", "--system", "air3d", "--budget", args.budget]
                    command += ["--seed", str(seed), *train_flags(fields), "--out", str(run)]
                    print("reach " + " ".join(command), flush=True)
                    if reach_main(command):
                        return 1
                meta = json.loads((run / "checkpoint.json").read_text())
                metrics = _score(run, gt)
                result = {"label": label, "seed": seed, "steps": meta["steps"], "wall_s": meta["wall_time_s"]}
                result.update(metrics)
                scored.write_text(json.dumps(result))
            rows.append(json.loads(scored.read_text()))
    print(f"\nAir3D, {budget:g} s budget each, scored against the 101^3 grid at t = 1.0 ({gt})\n")
    print("| recipe | seed | steps | train s | IoU volume | MSE volume | meets the goal |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for r in rows:
        meets = r["iou_volume"] >= GOAL["iou_volume"] and r["mse_volume"] <= GOAL["mse_volume"]
        print(f"| {r['label']} | {r['seed']} | {r['steps']} | {r['wall_s']:.0f} | {r['iou_volume']:.4f} | "
              f"{r['mse_volume']:.2e} | {'yes' if meets else 'no'} |")  # fmt: skip
    for label in RECIPES:
        mine = [r for r in rows if r["label"] == label]
        iou = [r["iou_volume"] for r in mine]
        mse = [r["mse_volume"] for r in mine]
        print(f"\n{label}: IoU mean {statistics.mean(iou):.4f} (min {min(iou):.4f}), "
              f"MSE mean {statistics.mean(mse):.2e} (max {max(mse):.2e}) over {len(mine)} seeds")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
