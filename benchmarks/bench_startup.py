"""What a ``reach`` command costs before and after its work: start-up and Python's shutdown.

Run: ``python benchmarks/bench_startup.py [--repeats 8]`` (``--quick``: 3 repeats)

Each repeat starts fresh processes side by side, in alternating order:

- ``python -c pass``: the interpreter alone;
- ``import torch``, then a normal exit;
- ``import torch``, then ``gc.freeze()`` before the exit (what the ``reach`` console script does,
  :func:`reach_cli.console_main`);
- ``reach envs`` through :func:`reach_cli.main` with a normal exit, and through ``console_main``.

It prints each one's median and range of wall times (seconds, start-up and exit included), and the
median per-repeat difference that freezing makes. Time it on a quiet machine: other work on the
cores moves these numbers by tens of percent.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

CASES = {
    "python alone": "pass",
    "import torch, normal exit": "import torch",
    "import torch, gc.freeze() at exit": "import gc, torch; gc.freeze()",
    "reach envs, main() then normal exit": "import sys; from reach_cli import main; sys.exit(main(['envs']))",
    "reach envs, console_main()": (
        "import sys; sys.argv = ['reach', 'envs']; from reach_cli import console_main; console_main()"
    ),
}
#: (without, with) pairs whose per-repeat difference is what freezing saves
PAIRS = (
    ("import torch, normal exit", "import torch, gc.freeze() at exit"),
    ("reach envs, main() then normal exit", "reach envs, console_main()"),
)


def measure(repeats: int) -> dict[str, list[float]]:
    walls: dict[str, list[float]] = {name: [] for name in CASES}
    for r in range(repeats):
        order = list(CASES) if r % 2 == 0 else list(reversed(CASES))  # alternate: no case always goes first
        for name in order:
            start = time.perf_counter()
            subprocess.run([sys.executable, "-c", CASES[name]], check=True, capture_output=True)
            walls[name].append(time.perf_counter() - start)
    return walls


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--quick", action="store_true", help="3 repeats (run_all.py --quick)")
    args = parser.parse_args()
    if args.quick:
        args.repeats = 3
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    walls = measure(args.repeats)
    print(f"# fresh processes, {args.repeats} repeats each, alternating order; python {sys.version.split()[0]}")
    print("| process | median s | min s | max s |")
    print("|---|---:|---:|---:|")
    for name, times in walls.items():
        print(f"| {name} | {statistics.median(times):.2f} | {min(times):.2f} | {max(times):.2f} |")
    print()
    for without, with_freeze in PAIRS:
        saved = [a - b for a, b in zip(walls[without], walls[with_freeze])]
        print(
            f"# {with_freeze!r} saves {statistics.median(saved):.2f} s (median of per-repeat differences; "
            f"range {min(saved):.2f} to {max(saved):.2f}) against {without!r}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
