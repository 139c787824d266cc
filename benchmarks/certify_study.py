"""Formal certification of a shipped value network by branch and bound (safety.formal.verifier): how much of
the state box is proven, refuted or left unknown at each level, and in what time.

Usage: ``python benchmarks/certify_study.py [--source pretrained:air3d] [--levels 0.05 0.1 0.2]
[--time-to-go 1.0] [--dt 0.02] [--max-seconds 120] [--device cpu|cuda] [--closure-width w]``

Each level runs the verifier (``safety.formal.verifier.certify``) from a fresh cover of the box until it
finishes or its time runs out; what is left counts as unknown. ``certified`` is yes only when every
box is outside the set or proven. Then ``safety.formal.closure.certified_set`` keeps the largest closed
union of the cover's safe boxes (cut down to ``--closure-width`` first, where given): ``kept`` is
its share of the box (the certified set is their union, with ``E`` where it holds), and with
``--out-dir`` its certificate is written there (the closure holds the boxes sparsely,
so it runs at 6D and 9D too). ``--explain`` says how the closure lost what it lost: the undecided
boxes from which every candidate input leaves the domain in one step, and the closure round by
round (boxes dropped, boxes kept by switching input, share of the box still kept; ``E`` marks the
rounds that assume the escape set of ``--escape-margin``, which holds only if no box of its band drops;
where it did not hold, a diagnostic closure that assumes it anyway says what the level set's band
alone leaves).

``--resume-dir`` keeps each level's verifier progress, so a second
run continues the first (its ``wall s`` and boxes count both): shares against time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch

from safety.formal.certificate import save_certificate
from safety.formal.closure import any_by_row, certified_set, closure_cover, closure_rows
from safety.formal.settings import REFUTED, UNKNOWN, CertificationResult, CertifySettings
from safety.formal.verifier import Verifier, certify, network_of
from safety.value_loading import load_value_function


def leaving_domain(network: object, result: CertificationResult) -> tuple[float, float]:
    """The undecided (refuted or unknown) boxes' share of the state box, and the share of those from
    which every candidate input takes some next state out of the domain in one step."""
    verifier = Verifier(network_of(network), result.settings, torch.device("cpu"))
    undecided = ((result.status == UNKNOWN) | (result.status == REFUTED)).nonzero().squeeze(-1)
    lo, hi = result.lo[undecided], result.hi[undecided]
    volume = ((hi - lo) / verifier.span).prod(-1)
    leaves = torch.ones(len(undecided), dtype=torch.bool)
    for u in verifier.candidates:
        n_lo, n_hi, piece = verifier.next_boxes(lo, hi, u.expand(len(lo), -1))
        leaves &= any_by_row(piece // len(verifier.d_lo), ~verifier.in_domain(n_lo, n_hi), len(lo))
    return float(volume.sum()), float(volume[leaves].sum())


def escape_assumed(network: object, result: CertificationResult) -> list[dict]:
    """The closure's rounds with the escape set assumed even where a box of its band drops (which
    makes ``E`` unsound): how much of the set the level set's band alone leaves."""
    verifier = Verifier(network_of(network), result.settings, torch.device("cpu"), closure=True)
    result, grid = closure_cover(result, verifier)
    rounds: list[dict] = []
    closure_rows(verifier, grid, result, rounds, torch.zeros(len(result.status), dtype=torch.bool))
    return rounds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default="pretrained:air3d")
    parser.add_argument("--levels", type=float, nargs="+", default=[0.05, 0.1, 0.2])
    parser.add_argument("--time-to-go", type=float, default=1.0)
    parser.add_argument("--dt", type=float, default=0.02)
    parser.add_argument("--integrator", default="euler")
    parser.add_argument("--max-seconds", type=float, default=120.0)
    parser.add_argument("--min-width", type=float, default=1 / 256)
    parser.add_argument("--initial-splits", type=int, default=8)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--max-boxes", type=int, default=2_000_000)
    parser.add_argument("--band-min-width", type=float, default=None, help="smallest box meeting the escape band")
    parser.add_argument(
        "--closure-width", type=float, default=None, help="cut boxes down to this width before the closure"
    )
    parser.add_argument("--closure-scale", type=int, default=1, help="close over the box widened this many times")
    parser.add_argument(
        "--escape-margin", type=float, default=None, help="m: the escape set {l >= m} (escape_rule)"
    )
    parser.add_argument("--out-dir", type=Path, default=None, help="write each level's certificate here")
    parser.add_argument("--explain", action="store_true", help="say how the closure lost what it lost")
    parser.add_argument(
        "--resume-dir",
        type=Path,
        default=None,
        help="keep each level's verifier progress here; run again to continue (wall s and boxes then add up)",
    )
    args = parser.parse_args()
    network = load_value_function(args.source).value_function
    print(
        f"# {args.source}: T = {args.time_to_go}, dt = {args.dt} ({args.integrator}), min width {args.min_width:g} "
        f"of the span, {args.max_seconds:g} s a level, device {args.device}"
    )
    print(
        "| level c | certified | finished | outside | escape | proven | refuted | unknown | boxes handled | wall s "
        "| counterexamples | kept | closure s |"
    )
    print("|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for level in args.levels:
        settings = CertifySettings(
            level=level,
            time_to_go=args.time_to_go,
            dt=args.dt,
            integrator=args.integrator,
            min_relative_width=args.min_width,
            initial_splits=args.initial_splits,
            batch=args.batch,
            max_seconds=args.max_seconds,
            max_boxes=args.max_boxes,
            escape_margin=args.escape_margin,
            band_min_relative_width=args.band_min_width,
            closure_relative_width=args.closure_width,
            closure_scale=args.closure_scale,
        )
        resume = None if args.resume_dir is None else args.resume_dir / f"level-{level:g}.progress.npz"
        result = certify(network, settings, device=args.device, resume=resume)
        shares = result.volume_shares()
        start = time.perf_counter()
        rounds: list[dict] = []
        certificate = certified_set(network, result, rounds)
        closure = f"{time.perf_counter() - start:.1f}"
        kept = f"{certificate.kept_volume_share(network.system.domain_tensor()):.4f}"
        if certificate.settings.escape_margin is not None:
            kept += f" + E ({len(certificate.escape)} boxes)"
        if args.out_dir is not None:
            save_certificate(args.out_dir / f"level-{level:g}.npz", certificate)
        print(
            f"| {level:g} | {'yes' if result.certified else 'no'} | {'yes' if result.finished else 'no'} | "
            f"{shares['outside']:.4f} | {shares['escape']:.4f} | {shares['proven']:.4f} | "
            f"{shares['refuted']:.4f} | {shares['unknown']:.4f} | {result.boxes_handled} | {result.wall_time:.1f} | "
            f"{len(result.counterexamples)} | {kept} | {closure} |",
            flush=True,
        )
        if args.explain:
            undecided, leaving = leaving_domain(network, result)
            print(
                f"#   c = {level:g}: undecided {undecided:.4f} of the box, of which {leaving:.4f} where every "
                f"input leaves the domain in one step; closure rounds (dropped / switched input / kept share):"
            )
            print(
                "#   "
                + ", ".join(f"{'E ' * r['escape']}{r['dropped']}/{r['switched']}/{r['kept']:.4f}" for r in rounds),
                flush=True,
            )
            if args.escape_margin is not None:
                print(f"#   band boxes not proven to hold only V >= c: {result.band_open}", flush=True)
                if certificate.settings.escape_margin is None:
                    assumed = escape_assumed(network, result)
                    print(
                        "#   diagnostic, not a certificate: the closure with E assumed whatever its band does: "
                        + ", ".join(f"{r['dropped']}/{r['switched']}/{r['kept']:.4f}" for r in assumed),
                        flush=True,
                    )


if __name__ == "__main__":
    main()
