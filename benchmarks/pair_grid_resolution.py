"""What pair-grid resolution keeps the union cap's benefit (issue 42, point 3): the compact pair grid.

Run: ``python benchmarks/pair_grid_resolution.py --fine runs/pair_gt.npz`` (the 101^3 solve,
``reach groundtruth relativepair --grid 101 --out runs/pair_gt.npz``). ``--write N --out FILE``
also writes the fine solve resampled to ``N^3`` nodes, the file that ships as
``pretrained:relativepair``.

For each resolution ``N`` it builds two compact pair grids of DeepReach's pair problem, the fine
solve resampled onto ``N^3`` nodes and a solve on ``N^3`` nodes, and measures on ``--samples``
uniform states of the 9D box, against the union from the fine grid at ``t = 1``:

- ``size MB``: the ``.npz`` file (float32, compressed, 11 times);
- ``miss %``: states the fine union puts in the BRT (``V <= 0``) and the compact one does not;
  ``extra %`` the reverse;
- ``max |dV| near 0``: the largest value difference where ``|V_fine| < 0.05``;
- ``cap flips %``: states where the shipped 9D network capped by the compact union and capped by
  the fine union disagree on the sign, i.e. on the learned BRT that filters and certificates use;
- ``capped misses %``: states of the fine union's BRT that the network capped by the compact union
  leaves out. The network alone misses more (printed first); the cap's benefit kept is the share
  of those misses the compact cap removes.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from groundtruth.pairwise import PairwiseUnion, solve_pairs
from groundtruth.solution import GridSolution
from reach.systems import MultiVehicle9D
from safety.value_loading import load_value_function

NEAR = 0.05


def _size_mb(solution: GridSolution) -> float:
    with tempfile.TemporaryDirectory() as d:
        return solution.save(Path(d) / "g.npz").stat().st_size / 1e6


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--fine", required=True, help="the 101^3 pair solve (.npz)")
    p.add_argument("--resolutions", default="31,41,51,61,71")
    p.add_argument("--samples", type=int, default=200_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--write", type=int, default=None, help="resample to N^3 and write --out")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    system = MultiVehicle9D()
    fine = GridSolution.load(args.fine, outside="clamp")
    if args.write is not None:
        if not args.out:
            p.error("--write needs --out")
        compact = fine.resampled(args.write)
        compact.save(args.out)
        print(f"wrote {args.out}: {fine.grid.shape} resampled to {compact.grid.shape}, {_size_mb(compact):.2f} MB")
        return 0
    x = system.sample_states(args.samples, generator=torch.Generator().manual_seed(args.seed), dtype=torch.float64)
    v_fine = PairwiseUnion(system, fine).value(x, 1.0)
    net = load_value_function("pretrained:multivehicle9d").value_function
    with torch.no_grad():
        v_net = net.value(x.float(), 1.0).double()
    cap_fine = torch.minimum(v_net, v_fine)
    near = v_fine.abs() < NEAR
    print(
        f"{args.samples} uniform 9D states (seed {args.seed}), t = 1; fine grid {fine.grid.shape}, "
        f"{_size_mb(fine):.1f} MB; fine union BRT {100 * float((v_fine <= 0).double().mean()):.2f} % of the box"
    )
    net_misses = float(((v_fine <= 0) & (v_net > 0)).double().mean())
    print(f"the shipped 9D network alone misses {100 * net_misses:.3f} % of the box of the fine union's BRT")
    print(
        "| N^3 | made by | size MB | miss % | extra % | max abs dV near 0 | cap flips % | capped misses % "
        "| benefit kept % | build s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n in (int(r) for r in args.resolutions.split(",")):
        for how in ("resampled", "solved"):
            start = time.perf_counter()
            if how == "resampled":
                compact = fine.resampled(n)
            else:
                (compact,) = solve_pairs(system, grid=n, times=fine.times.tolist()).values()
            built = time.perf_counter() - start
            v = PairwiseUnion(system, compact).value(x, 1.0)
            miss = float(((v_fine <= 0) & (v > 0)).double().mean())
            extra = float(((v_fine > 0) & (v <= 0)).double().mean())
            dv = float((v - v_fine)[near].abs().max())
            capped = torch.minimum(v_net, v)
            flips = float(((capped <= 0) != (cap_fine <= 0)).double().mean())
            capped_misses = float(((v_fine <= 0) & (capped > 0)).double().mean())
            kept = 100 * (1 - capped_misses / net_misses) if net_misses > 0 else float("nan")
            print(
                f"| {n} | {how} | {_size_mb(compact):.2f} | {100 * miss:.3f} | {100 * extra:.3f} | {dv:.4f} "
                f"| {100 * flips:.3f} | {100 * capped_misses:.3f} | {kept:.1f} | {built:.1f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
