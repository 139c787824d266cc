"""How much the thread policy gains beside low-priority work: ``reach train`` steps in a fixed budget.

Starts one ``nice -n 19`` CPU-bound process per usable core, then runs the same short ``reach train``
twice, side by side in one run of this script (one after the other, the niced load unchanged):

* ``--threads 1``: what the earlier policy chose there (it counted every runnable thread as a busy
  core, whatever its priority, so it left torch one thread);
* the default: the current policy, which counts only work at this process's priority or higher
  (:func:`reach.threads.competing_runnable`), so it takes every core: the niced jobs yield.

Prints the thread count each policy chose and the steps each run made. Run it on a machine with
nothing else running at normal priority::

    python benchmarks/thread_policy_nice.py --budget 60s
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from reach.threads import free_cores, usable_cores


def _train(budget: str, threads: list[str], out: Path) -> int:
    """The steps ``reach train`` made in ``budget`` (from its closing line: ``RUN: N steps in S s``)."""
    argv = [sys.executable, "-m", "reach", *threads, "train", "--system", "air3d", "--budget", budget]
    done = subprocess.run([*argv, "--out", str(out)], check=True, capture_output=True, text=True)
    return int(re.search(r": (\d+) steps in ", done.stdout).group(1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--budget", default="60s", help="each run's wall-clock budget")
    args = parser.parse_args()
    spin = [sys.executable, "-c", "while True: pass"]
    load = [subprocess.Popen(["nice", "-n", "19", *spin]) for _ in range(usable_cores())]
    try:
        chosen = free_cores()
        print(f"{len(load)} niced CPU-bound processes; the policy chooses {chosen} thread(s) of {usable_cores()}")
        with tempfile.TemporaryDirectory() as tmp:
            for label, threads in (("one thread (earlier policy)", ["--threads", "1"]), ("policy default", [])):
                run = Path(tmp) / label.split()[0]
                steps = _train(args.budget, threads, run)
                print(f"{label:>28}: {steps} steps in {args.budget}")
    finally:
        for p in load:
            p.kill()
            p.wait()


if __name__ == "__main__":
    main()
