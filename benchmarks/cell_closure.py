"""How much of Air3D a one-step box certificate can hold at all: the closure of a uniform cover.

Run: ``python benchmarks/cell_closure.py [--cells 64 64 64] [--escape-margin 0.75] [--dt 0.02]``
(``--closure-scale 4 --escape-margin 3.75``: close over the box widened four times; ``--out CERT``
writes the certificate, which ``reach certify pretrained:air3d --check CERT`` re-verifies)

The certified set of :func:`safety.formal.closure.certified_set` is a union of boxes, each with one
backup input, whose next states land in the union (or in the escape set ``E``). This study asks
what such a set can be with no help from a value function: every cell of a uniform grid over the
state box is a candidate (none is marked proven, so no next state may lean on ``V >= c``), each
tries every candidate input (the control box's vertices and centre), and the library's closure
keeps the largest closed union. It prints the kept share of the box; whether ``E`` held (every cell
meeting the band below it kept); and, as a diagnostic that is **not** a certificate, the closure
with ``E`` assumed even where its band drops, with how many band cells dropped. Compare the shares
with the largest invariant set (``benchmarks/invariant_reference.py``). The value network named
by ``--source`` is loaded only because the verifier is built around one; nothing of it is used.
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import torch

from safety.formal.certificate import save_certificate, volume_share
from safety.formal.closure import certified_set, closure_cover, closure_rows
from safety.formal.settings import ESCAPE, UNKNOWN, CertificationResult, CertifySettings
from safety.formal.verifier import Verifier, candidate_inputs, network_of
from safety.value_loading import load_value_function


def uniform_cover(domain: torch.Tensor, cells: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """The corners of a uniform grid of ``cells`` per dimension over ``domain``."""
    edges = [torch.linspace(float(a), float(b), n + 1, dtype=torch.float64) for (a, b), n in zip(domain, cells)]
    index = torch.tensor(list(itertools.product(*[range(n) for n in cells])), dtype=torch.long)
    lo = torch.stack([edges[d][index[:, d]] for d in range(len(cells))], -1)
    hi = torch.stack([edges[d][index[:, d] + 1] for d in range(len(cells))], -1)
    return lo, hi


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default="pretrained:air3d")
    parser.add_argument("--cells", type=int, nargs="+", default=[64, 64, 64])
    parser.add_argument("--escape-margin", type=float, default=0.75)
    parser.add_argument("--dt", type=float, default=0.02)
    parser.add_argument("--integrator", default="euler")
    parser.add_argument("--closure-scale", type=int, default=1, help="close over the box widened this many times")
    parser.add_argument("--refinements", type=int, default=0, help="closure_refinements: cut at the set's edge")
    parser.add_argument("--out", type=Path, default=None, help="write the certificate here (.npz)")
    args = parser.parse_args()
    network = network_of(load_value_function(args.source).value_function)
    domain = network.system.domain_tensor(torch.float64, "cpu")
    if len(args.cells) != len(domain) or any(n < 1 or n & (n - 1) for n in args.cells):
        parser.error(f"--cells needs {len(domain)} powers of two, got {args.cells}")
    settings = CertifySettings(
        level=0.0, time_to_go=network.system.horizon, dt=args.dt, integrator=args.integrator,
        escape_margin=args.escape_margin, closure_scale=args.closure_scale,
        closure_relative_width=1 / min(args.cells), closure_refinements=args.refinements,
    )  # fmt: skip
    lo, hi = uniform_cover(domain, args.cells)
    verifier = Verifier(network, settings, torch.device("cpu"), closure=True)
    status = torch.where(verifier.in_escape(lo, hi), torch.tensor(ESCAPE), torch.tensor(UNKNOWN))
    result = CertificationResult(
        settings, lo, hi, status, torch.full((len(lo),), -1, dtype=torch.long), candidate_inputs(network)
    )
    wide, grid = closure_cover(result, verifier)  # the closure's cover (the network's box, or more)
    lo, hi, status = wide.lo, wide.hi, wide.status
    domain = verifier.domain
    band = verifier.in_band(lo, hi) & (status != ESCAPE)
    print(
        f"# {args.source}: {'x'.join(map(str, args.cells))} cells, dt = {args.dt} ({args.integrator}), "
        f"E = {{l >= {args.escape_margin:g}}}: {int((status == ESCAPE).sum())} cells in E, "
        f"{int(band.sum())} meet its band"
    )
    start = time.perf_counter()
    rounds: list[dict] = []
    certificate = certified_set(network, result, rounds)
    held = certificate.settings.escape_margin is not None
    if args.out is not None:
        save_certificate(args.out, certificate)

    def share(box_lo: torch.Tensor, box_hi: torch.Tensor) -> float:
        return volume_share(box_lo, box_hi, verifier.network_domain)  # of the network's box

    e_share = share(certificate.escape.lo, certificate.escape.hi)
    print(
        f"certificate: kept {share(certificate.kept.lo, certificate.kept.hi):.4f} of the network's box, "
        f"E {'held' if held else 'did not hold'} (+{e_share:.4f}), {len(rounds)} rounds, "
        f"{time.perf_counter() - start:.1f} s"
    )
    if held:
        print("E held: the certificate is the closure with E assumed")
        return
    start = time.perf_counter()
    assumed = closure_rows(verifier, grid, wide, None, torch.zeros(len(lo), dtype=torch.bool))
    assert assumed is not None
    rows = assumed[0]
    kept_assumed = share(lo[rows], hi[rows])
    in_e = share(lo[status == ESCAPE], hi[status == ESCAPE])
    survived = torch.zeros(len(lo), dtype=torch.bool)
    survived[rows] = True
    print(
        f"diagnostic, not a certificate (E assumed whatever its band does): kept {kept_assumed:.4f} of the "
        f"network's box "
        f"(+{in_e:.4f} in E), {int((band & ~survived).sum())} of {int(band.sum())} band cells dropped, "
        f"{time.perf_counter() - start:.1f} s"
    )


if __name__ == "__main__":
    main()
