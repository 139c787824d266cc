"""Run every benchmark script, one after another, and print a summary table.

Run: ``python benchmarks/run_all.py --out bench-results`` (``--quick`` for smoke runs, ``--only
rollouts envs`` for some, ``--compare OLD/summary.json`` to put an earlier run's wall times beside).

Each script (environment throughput, grid solver, one solver right-hand side, the grid solver
against hj_reachability, training step, rollouts) runs in its own process, never two at once (they
would time each other), with its full output kept in ``OUT/<name>.txt``.
The summary lists exit status and wall time per script, and ``OUT/report.md`` gathers every
script's markdown tables under its command line, for the README or for comparing machines.
``OUT/summary.json`` holds the same, plus versions, for ``--compare``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: name -> script and its arguments; "hj_reachability" installs that library in a virtual environment
#: of its own on first use (benchmarks/hj_comparison.py), never into this one
SCRIPTS = {
    "envs": ["bench_envs.py"],
    "groundtruth": ["bench_groundtruth.py"],
    "rhs": ["bench_rhs.py", "--grids", "51", "101"],
    "hj_reachability": ["bench_groundtruth.py", "--against", "hj_reachability"],
    "training": ["bench_training.py"],
    "rollouts": ["bench_rollouts.py"],
    "startup": ["bench_startup.py"],
}


def tables(text: str) -> str:
    """The markdown table lines (and '#' comment lines) of a script's output."""
    keep = [line for line in text.splitlines() if line.startswith("|") or line.startswith("#")]
    return "\n".join(keep)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bench-results", help="directory for outputs and the summary")
    parser.add_argument("--quick", action="store_true", help="pass --quick to every script")
    parser.add_argument("--only", nargs="+", choices=sorted(SCRIPTS), default=None)
    parser.add_argument("--compare", default=None, help="an earlier summary.json to compare wall times with")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = args.only or list(SCRIPTS)
    previous = {}
    if args.compare:
        previous = {r["name"]: r for r in json.loads(Path(args.compare).read_text())["runs"]}
    runs = []
    env = {**os.environ, "TQDM_DISABLE": "1", "MPLBACKEND": "Agg"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE.parent), env.get("PYTHONPATH")]))
    for name in names:
        script, *script_args = SCRIPTS[name]
        cmd = [sys.executable, str(HERE / script), *script_args] + (["--quick"] if args.quick else [])
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=HERE.parent)
        wall = time.perf_counter() - start
        (out / f"{name}.txt").write_text(proc.stdout + proc.stderr)
        runs.append(
            {
                "name": name,
                "command": " ".join(["python", f"benchmarks/{script}", *cmd[2:]]),
                "exit": proc.returncode,
                "wall_s": wall,
                "tables": tables(proc.stdout),
            }
        )
        print(f"{name}: exit {proc.returncode} in {wall:.1f} s", file=sys.stderr)
    header = "| benchmark | exit | wall (s) |" + (" previous wall (s) | ratio |" if previous else "")
    lines = [header, "|---|---|---|" + ("---|---|" if previous else "")]
    for r in runs:
        row = f"| {r['name']} | {r['exit']} | {r['wall_s']:.1f} |"
        if previous:
            old = previous.get(r["name"])
            row += f" {old['wall_s']:.1f} | {r['wall_s'] / old['wall_s']:.2f} |" if old else " - | - |"
        lines.append(row)
    summary = "\n".join(lines)
    print(summary)
    machine = f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}"
    report = [f"# Benchmarks ({machine})", "", summary, ""]
    for r in runs:
        report += [f"## {r['name']}: `{r['command']}`", "", r["tables"], ""]
    (out / "report.md").write_text("\n".join(report))
    (out / "summary.json").write_text(json.dumps({"machine": machine, "quick": args.quick, "runs": runs}, indent=2))
    print(f"wrote {out / 'report.md'} and {out / 'summary.json'}")
    return 0 if all(r["exit"] == 0 for r in runs) else 1


if __name__ == "__main__":
    raise SystemExit(main())
