"""``reach certify``: a formally certified safe set of a value network, and the check of a certificate file.

Wiring only: the options become a :class:`~safety.formal.settings.CertifySettings` (options left out fall back
to its defaults); :func:`~safety.formal.verifier.certify` proves boxes, :func:`~safety.formal.closure.certified_set`
keeps the largest closed union of them, and the file is written atomically. ``--check CERT`` re-verifies
a file for the value function named, from the file alone.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from reach.exit_codes import EXIT_PARTIAL
from reach.validation import (
    check_output_path,
    device_arg,
    finite_float_arg,
    nonnegative_int_arg,
    positive_float_arg,
    positive_int_arg,
    unit_interval_arg,
)
from reach_cli.options import add_subparser, default
from safety.formal.settings import CertifySettings, certify_defaults

#: (option, CertifySettings field, argparse keywords, help) of the verifier's knobs
CERTIFY_OPTIONS = (
    ("--integrator", "integrator", {"choices": ["euler", "rk4"]}, "the env's integrator, which the proof steps with"),
    ("--disturbance-splits", "disturbance_splits", {"type": positive_int_arg}, "pieces per disturbance dimension"),
    ("--initial-splits", "initial_splits", {"type": positive_int_arg}, "the first cover's boxes per dimension"),
    ("--min-width", "min_relative_width", {"type": unit_interval_arg}, "smallest box (share of the span)"),
    ("--batch", "batch", {"type": positive_int_arg}, "boxes bounded at once"),
    ("--max-boxes", "max_boxes", {"type": positive_int_arg}, "stop after this many boxes (the rest: unknown)"),
    ("--max-seconds", "max_seconds", {"type": positive_float_arg}, "stop after this wall time (the rest: unknown)"),
    (
        "--band-min-width",
        "band_min_relative_width",
        {"type": unit_interval_arg},
        "smallest box meeting the escape set's band (share of the span)",
    ),
    (
        "--closure-width",
        "closure_relative_width",
        {"type": unit_interval_arg},
        "cut boxes down to this width (share of the span) before the closure, each with its own input",
    ),
    (
        "--closure-scale",
        "closure_scale",
        {"type": positive_int_arg},
        "close over the state box widened this many times (a power of two; needs --closure-width)",
    ),
    (
        "--closure-refinements",
        "closure_refinements",
        {"type": nonnegative_int_arg},
        "cut the dropped boxes near the set's edge into halves and close again, this many times",
    ),
    (
        "--closure-refine-reach",
        "closure_refine_reach",
        {"type": positive_int_arg},
        "near: within this many of the box's own widths of a kept box",
    ),
    (
        "--escape-margin",
        "escape_margin",
        {"type": positive_float_arg},
        "m: states with l >= m form an escape set, certified by the system's lemmas, not the network",
    ),
)


def add_parser(sub: Any) -> None:
    p = add_subparser(
        sub, "certify", help="prove a safe set {V >= c} invariant by branch and bound, or check a certificate file"
    )
    p.add_argument("source", help="value function: a run, .pt or pretrained:NAME (a neural avoid problem)")
    p.add_argument("--check", metavar="CERT", default=None, help="re-verify this certificate file for SOURCE")
    p.add_argument(
        "--level", type=finite_float_arg, default=None, help="c: the set is {V(x, T) >= c} (default: the system's)"
    )
    p.add_argument("--time-to-go", type=positive_float_arg, default=None, help="T (default: the system's horizon)")
    p.add_argument("--dt", type=positive_float_arg, default=None, help="the env's step (default: the env scenes' step)")
    for option, field, kwargs, text in CERTIFY_OPTIONS:
        p.add_argument(
            option, dest=field, default=None, help=f"{text} (default: {default(CertifySettings, field)})", **kwargs
        )
    p.add_argument(
        "--device", type=device_arg, default="cpu", help="where boxes are bounded (a GPU: many more a second)"
    )
    p.add_argument("--out", default=None, help="the certificate file to write (.npz)")
    p.add_argument(
        "--resume",
        metavar="PROGRESS",
        default=None,
        help="keep the verifier's progress in this .npz file; run again with it to continue a stopped run",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # lazy: the verifier's stack only when this command runs
    from safety.formal.certificate import save_certificate
    from safety.formal.checker import check_certificate
    from safety.formal.closure import certified_set
    from safety.formal.verifier import certify, network_of
    from safety.value_loading import load_value_function

    if args.check is not None:
        if args.out is not None or args.level is not None or args.resume is not None:
            raise ValueError("--check re-verifies a file as it is: give no --level, --out or --resume with it")
        value_function = load_value_function(args.source).value_function
        certificate = check_certificate(args.check, value_function, args.device)
        s = certificate.settings
        print(
            f"{args.check}: holds for {args.source}: {len(certificate.kept)} boxes certified at level {s.level:g}, "
            f"T = {s.time_to_go:g}, dt = {s.dt:g} ({s.integrator})"
        )
        return 0
    if args.out is None:
        raise ValueError("give --out CERT.npz (or --check CERT to re-verify a file)")
    if not str(args.out).endswith(".npz"):
        raise ValueError(f"--out: a certificate file ends in .npz, got {args.out!r}")
    out = check_output_path(args.out, "--out")  # a folder, a device or an unwritable place: before the proof
    if args.resume is not None:
        check_output_path(args.resume, "--resume")
        if Path(args.resume).resolve() == out.resolve():
            raise ValueError(
                f"--out and --resume name the same file ({args.out}): the certificate would overwrite the progress"
            )
    if args.dt is None:
        from reach_envs.scenes import Scene  # lazy: the env stack (gymnasium) only for this default

        args.dt = default(Scene, "dt")
    value_function = load_value_function(args.source).value_function
    given = {field: getattr(args, field) for _, field, _, _ in CERTIFY_OPTIONS if getattr(args, field) is not None}
    if args.level is not None:
        given["level"] = args.level
    system = value_function.system
    # the system's certification defaults (declared beside its lemmas, or derived from them) fill what
    # the options leave out; the options stay for experts
    integrator = given.get("integrator", default(CertifySettings, "integrator"))
    used = certify_defaults(system, args.dt, integrator, given)
    if used:
        shown = ", ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}" for k, v in used.items())
        print(f"{system.name}'s certification defaults: {shown}")
    time_to_go = args.time_to_go if args.time_to_go is not None else system.horizon
    settings = CertifySettings(time_to_go=time_to_go, dt=args.dt, **{**used, **given})
    network_of(value_function)  # a grid or a composition is refused before any work, naming what it takes
    result = certify(value_function, settings, device=args.device, resume=args.resume)
    certificate = certified_set(value_function, result)
    path = save_certificate(args.out, certificate)
    shares = result.volume_shares()
    domain = value_function.system.domain_tensor()
    ended = "finished" if result.finished else "stopped"
    if not result.finished and args.resume:
        ended += f" (continue with --resume {args.resume})"
    print(
        f"{ended} after {result.boxes_handled} boxes in {result.wall_time:.1f} s: "
        + ", ".join(f"{name} {share:.4f}" for name, share in shares.items())
        + f" of the state box; {len(result.counterexamples)} counterexamples"
    )
    share = certificate.kept_volume_share(domain)
    m = certificate.settings.escape_margin
    escape = f", and the escape set l >= {m:g}" if m is not None else ""
    if m is None and settings.escape_margin is not None:
        escape = " (the escape set did not hold: a box of the band below it was not kept; written without it)"
    beyond = certificate.kept_beyond(domain)
    print(
        f"wrote {path}: {len(certificate.kept)} boxes, {share:.4f} of the state box"
        + (f" (and {beyond} of the boxes beyond it)" if beyond else "")
        + ", "
        f"certified invariant and safe where V >= {settings.level:g}{escape}"
        + ("" if result.certified else " (the rest of {V >= c} is not certified)")
    )
    return 0 if len(certificate.kept) else EXIT_PARTIAL
