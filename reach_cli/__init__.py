"""``reach``: the command line of the reach toolkit.

Each subcommand is one module of this package holding its parser beside its handler: ``envs``
(list environments and scenes), ``pretrained`` (the shipped value networks and their cards),
``record`` (an episode as a GIF), ``groundtruth`` (grid BRT solve), ``train`` (value networks),
``train-until`` (training in phases until the scenario bound holds), ``evaluate`` (rollout
verification across checkpoints), ``filter-eval`` (what a safety filter changes in episodes of a
task), ``fleet-eval`` (fleet filters against the fleet's size), ``fleet-replay`` (one of its
collided episodes, alone), ``export`` (a filter as one ONNX file for the torch-free runtime),
``certify`` (a formally certified safe set, or the check of its file), ``plot`` (BRT slices, union overlays, violation
bars, filtered-episode GIFs), ``sweep`` (layouts x seeds on a budget, with a report) and ``demo``
(all of it on Air3D).

Handlers only parse and call library functions. Options that mirror a library setting default to
``None`` and fall back to the library's dataclass, so every default has one source; ``--help``
prints those defaults. Every value is checked by the option's type or by the library's own
validation before any expensive work starts.

Errors: any expected failure (a bad value, a missing or unreadable file, a locked run directory) is
printed as one line naming the bad value, with exit status 2; ``--debug`` shows the traceback
instead. A command that ran but failed in part (a source of ``reach evaluate`` that did not load, a
training run that diverged) exits with 3, after writing what succeeded. An interrupted command
(Ctrl-C, SIGTERM) exits with 130 after saving what it can.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
from collections.abc import Callable, Sequence

import torch

from reach.exit_codes import EXIT_BROKEN_PIPE, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_USAGE
from reach.threads import apply_thread_policy
from reach_cli import (
    certify,
    demo,
    envs,
    evaluate,
    export,
    filter_eval,
    fleet_eval,
    fleet_replay,
    groundtruth,
    plot,
    pretrained,
    record,
    sweep,
    train,
    train_until,
)
from reach_cli.options import OneLineParser, common_options, finish_namespace

#: subcommand modules, in the order ``reach --help`` lists them
COMMANDS = (
    envs,
    pretrained,
    record,
    groundtruth,
    train,
    train_until,
    evaluate,
    filter_eval,
    fleet_eval,
    fleet_replay,
    export,
    certify,
    plot,
    sweep,
    demo,
)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="reach", description="Neural Hamilton-Jacobi reachability toolkit.", parents=[common_options()]
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    sub.required = True
    for module in COMMANDS:
        module.add_parser(sub)
    return parser


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split()) or type(err).__name__
    return text if len(text) <= 600 else text[:597] + "..."


def main(argv: Sequence[str] | None = None) -> int:
    args = finish_namespace(build_parser().parse_args(argv))
    if args.debug:
        return _run(args)
    return guarded(f"reach {args.command}", lambda: _run(args))


def guarded(command: str, work: Callable[[], int], catch_bugs: bool = True) -> int:
    """Run ``work`` behind the command line's error boundary, as ``command`` (e.g. ``"reach train"``,
    or a study script's name): its status, or, for an expected failure (a bad value, an unreadable
    file, a locked run), one line on stderr and :data:`~reach.exit_codes.EXIT_USAGE`; an interrupt
    (Ctrl-C, SIGTERM, after the work saved what it can) one line and ``EXIT_INTERRUPTED``; a reader
    that went away ``EXIT_BROKEN_PIPE``; a bug one line naming it and ``EXIT_INTERNAL`` (with
    ``catch_bugs=False``, as the study scripts have no ``--debug``, its traceback instead)."""
    try:
        return work()
    except BrokenPipeError:  # the reader closed the pipe: nothing to report, and nobody to report it to
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # so the exit's flush cannot fail
        return EXIT_BROKEN_PIPE
    except KeyboardInterrupt as err:  # TrainingInterrupted says what was saved
        print(f"{command}: interrupted{': ' + _one_line(err) if str(err) else ''}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as err:
        print(f"{command}: error: {_one_line(err)}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as err:  # a bug, not bad input: still one line, with the way to the traceback
        if not catch_bugs:
            raise
        print(
            f"{command}: internal error: {type(err).__name__}: {_one_line(err)} (rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL


def console_main() -> None:
    """The ``reach`` console script (and ``python -m reach``): :func:`main`, then exit without
    Python's shutdown garbage pass over torch's objects.

    That pass walks every object ``import torch`` leaves behind; skipping it shortens each command's exit
    (measured: docs/results/benchmarks.md, *Command start-up*).
    A command's results are written and closed before :func:`main` returns, and Python does not
    promise to finalise objects still alive at exit anyway. Only the console script does this:
    :func:`main` called in-process leaves the caller's collector alone."""
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    gc.freeze()
    sys.exit(code)


def _run(args: argparse.Namespace) -> int:
    before = torch.get_num_threads()
    if args.command != "sweep":  # a sweep sets threads per run itself (--threads there means per run)
        apply_thread_policy(args.threads)
    try:
        return int(args.func(args))
    finally:  # main() called in-process (tests, scripts) leaves the caller's thread count as it was
        torch.set_num_threads(before)


__all__ = ["build_parser", "console_main", "guarded", "main"]
