"""How tight safety.formal.bounds' sound bounds are: their width against the network's own range on small boxes.

Usage: ``python benchmarks/bound_tightness.py [--source pretrained:air3d ...] [--boxes 64]``

For each value network and box size (half-widths uniform in ``[0, 10**k]`` of the domain's span per
dimension, time likewise, centres uniform), the median over the boxes of each bound's width divided by
the linearised range ``2 sum |do/dz_i(centre)| r_i`` (autograd at the centre: the range the bound would
have if the network were linear on the box). 1 is as tight as a bound can be on small boxes; IBP
stays a constant factor above it however small the box, the mean-value form tends to 1.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from safety.formal.bounds import interval_bounds, mean_value_bounds
from safety.formal.linear_bounds import linear_bounds
from safety.value_loading import load_value_function


def boxes(network, count: int, log_half_width: float, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    domain = network.system.domain_tensor(torch.float64, "cpu")
    span = domain[:, 1] - domain[:, 0]
    half = span * 10.0**log_half_width * torch.rand((count, len(span)), generator=g, dtype=torch.float64)
    centre = domain[:, 0] + span * torch.rand((count, len(span)), generator=g, dtype=torch.float64)
    horizon = network.system.horizon
    t_c = horizon * torch.rand(count, generator=g, dtype=torch.float64)
    t_half = horizon * 10.0**log_half_width * torch.rand(count, generator=g, dtype=torch.float64)
    return centre - half, centre + half, t_c - t_half, t_c + t_half


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", nargs="+", default=["pretrained:air3d", "pretrained:multivehicle9d"])
    parser.add_argument("--boxes", type=int, default=64)
    parser.add_argument("--sizes", type=float, nargs="+", default=[-2, -3, -4, -5])
    args = parser.parse_args()
    print(
        "| model | box half-width / span | IBP / linear range | mean-value / linear range | CROWN-style / linear range "
        "| forward intervals / linear range | ms a box: IBP + mean-value, CROWN-style, forward |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for source in args.source:
        network = load_value_function(source).value_function.network.double()
        for k in args.sizes:
            x_lo, x_hi, t_lo, t_hi = boxes(network, args.boxes, k)
            start = time.perf_counter()
            ibp = interval_bounds(network, x_lo, x_hi, t_lo, t_hi)
            mvf = mean_value_bounds(network, x_lo, x_hi, t_lo, t_hi)
            ms = (time.perf_counter() - start) / args.boxes * 1e3
            start = time.perf_counter()
            crown = linear_bounds(network, x_lo, x_hi, t_lo, t_hi)
            ms_crown = (time.perf_counter() - start) / args.boxes * 1e3
            start = time.perf_counter()
            forward = linear_bounds(network, x_lo, x_hi, t_lo, t_hi, intermediate="forward")
            ms_forward = (time.perf_counter() - start) / args.boxes * 1e3
            x = (0.5 * (x_lo + x_hi)).requires_grad_(True)
            t = (0.5 * (t_lo + t_hi)).requires_grad_(True)
            gx, gt = torch.autograd.grad(network.raw(x, t).sum(), (x, t))
            linear = 2 * ((gx.abs() * 0.5 * (x_hi - x_lo)).sum(-1) + gt.abs() * 0.5 * (t_hi - t_lo))
            r_ibp = statistics.median(((ibp[1] - ibp[0]) / linear).tolist())
            r_mvf = statistics.median(((mvf[1] - mvf[0]) / linear).tolist())
            r_crown = statistics.median(((crown[1] - crown[0]) / linear).tolist())
            r_forward = statistics.median(((forward[1] - forward[0]) / linear).tolist())
            print(
                f"| {source} | up to 1e{k:g} | {r_ibp:.1f} | {r_mvf:.2f} | {r_crown:.2f} | {r_forward:.2f} "
                f"| {ms:.2f}, {ms_crown:.2f}, {ms_forward:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
