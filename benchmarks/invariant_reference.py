"""The largest invariant set of Air3D in the certification box, and a certificate's share of it.

Run: ``python benchmarks/invariant_reference.py [--certificate runs/union/level-0.02.npz]``
(``--half-width 2 --nodes 121 121 61 --times 1 2 3 --samples 1000000 --cache runs/air3d-wide.npz``).

The largest invariant set of an avoid game is the complement of its converged backward reachable
tube. The grid solver solves Air3D on a domain wider than the network's (``|x1|, |x2| <= 2``, so
the tube never meets the grid's edge) to several times-to-go; at uniform samples of the
certification box ``[-1, 1]^2 x [-pi, pi]`` the script prints the tube's share at each time, and
how much it still grew since the time before (converged when that is near zero). The last time's
complement is the reference.

With ``--certificate``, it also prints the certified set's share of the box (the kept boxes and, if
the certificate has one, the escape set ``E``), its share of the reference, and the share of
certified samples that the grid puts in the tube (zero up to the grid's error: a certified state
cannot be in the tube, which the certificate proves for the discrete-time model); ``--plot PNG``
draws x1-x2 slices of both.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from groundtruth import GridSolution, solve
from reach.systems import Air3D
from safety.formal.certificate import load_certificate
from safety.formal.cover import CellGrid, DyadicCover
from safety.formal.settings import closure_domain


def certified_mask(path: Path, x: torch.Tensor) -> torch.Tensor:
    """Whether each state lies in the certificate's set: a kept box, or the escape set ``E``."""
    certificate = load_certificate(path)
    system = Air3D()
    domain = closure_domain(system, certificate.settings.closure_scale)
    every = certificate.every_box()
    grid = CellGrid(domain, certificate.resolution, every.lo, every.hi)
    cover = DyadicCover(*grid.cells(certificate.kept.lo, certificate.kept.hi, exact=True), grid.resolution)
    cells = ((x - domain[:, 0]) / grid.span * grid.resolution).floor().long().clamp(0, grid.resolution - 1)
    inside = cover.owner(cells) >= 0
    if certificate.settings.escape_margin is not None:
        inside |= system.failure_margin(x) >= certificate.settings.escape_margin
    return inside


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--half-width", type=float, default=2.0)
    parser.add_argument("--nodes", type=int, nargs=3, default=[121, 121, 61])
    parser.add_argument("--times", type=float, nargs="+", default=[1.0, 2.0, 3.0])
    parser.add_argument("--samples", type=int, default=1_000_000)
    parser.add_argument("--cache", type=Path, default=Path("runs/air3d-wide.npz"))
    parser.add_argument("--certificate", type=Path, default=None)
    parser.add_argument("--plot", type=Path, default=None, help="with --certificate: draw slices of both here")
    args = parser.parse_args()
    wide = Air3D(half_width=args.half_width, horizon=max(args.times))
    start = time.perf_counter()
    if args.cache.exists():
        solution = GridSolution.load(args.cache)
        how = f"loaded from {args.cache}"
    else:
        solution = solve(wide, args.nodes, args.times)
        args.cache.parent.mkdir(parents=True, exist_ok=True)
        solution.save(args.cache)
        how = f"solved in {time.perf_counter() - start:.0f} s, saved to {args.cache}"
    print(f"# Air3D on |x1|, |x2| <= {args.half_width:g}, {'x'.join(map(str, args.nodes))} nodes: {how}")
    box = Air3D()
    x = box.sample_states(args.samples, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    print("| time-to-go | tube's share of the box | grown since the time before |")
    print("|---:|---:|---:|")
    before = None
    for t in args.times:
        tube = solution.value(x.float(), t) <= 0
        share = float(tube.double().mean())
        grown = "" if before is None else f"{share - before:.4f}"
        print(f"| {t:g} | {share:.4f} | {grown} |")
        before = share
    invariant = ~tube
    print(f"# reference: the largest invariant set is {float(invariant.double().mean()):.4f} of the box")
    if args.certificate is not None:
        certified = certified_mask(args.certificate, x)
        share = float(certified.double().mean())
        covered = float((certified & invariant).double().sum() / invariant.double().sum())
        wrong = float((certified & tube).double().sum() / certified.double().sum().clamp(min=1))
        print(
            f"# {args.certificate}: certified {share:.4f} of the box, {covered:.4f} of the largest invariant set; "
            f"{wrong:.5f} of certified samples in the grid's tube ({args.samples} uniform samples)"
        )
        if args.plot is not None:
            plot_slices(args.plot, args.certificate, solution, max(args.times))


def plot_slices(path: Path, certificate: Path, solution: GridSolution, t: float, n: int = 400) -> None:
    """x1-x2 slices of the box at Air3D's plotted headings: the certified set, the rest of the largest
    invariant set, and the tube."""
    # lazy: matplotlib only when a plot is asked for
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    slices = Air3D().plot_slices()
    fig, axes = plt.subplots(1, len(slices), figsize=(4.2 * len(slices), 4.2))
    axis = torch.linspace(-1.0, 1.0, n, dtype=torch.float64)
    x1, x2 = torch.meshgrid(axis, axis, indexing="xy")
    colours = ListedColormap(["#d62728", "#c7c7c7", "#2ca02c"])
    for ax, (point, _, label) in zip(axes, slices):
        x = torch.stack([x1.reshape(-1), x2.reshape(-1), torch.full((n * n,), point[2], dtype=torch.float64)], -1)
        tube = solution.value(x.float(), t) <= 0
        kind = torch.where(tube, 0, torch.where(certified_mask(certificate, x), 2, 1)).reshape(n, n)
        ax.imshow(kind.numpy(), origin="lower", extent=(-1, 1, -1, 1), cmap=colours, vmin=0, vmax=2)
        ax.set_title(label)
        ax.set_xlabel("x1")
        ax.set_ylabel("x2")
    fig.suptitle("green: formally certified; grey: safe (grid), not certified; red: the tube")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    main()
