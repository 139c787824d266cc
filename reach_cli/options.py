"""Pieces the subcommands share: global options, defaults read from the library, output checks."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
from typing import Any, NoReturn

from reach.validation import positive_int_arg


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line (``reach train: error: ...``), exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def common_options(threads: bool = True) -> argparse.ArgumentParser:
    """``--debug`` and ``--threads``, accepted before or after the subcommand."""
    parent = OneLineParser(add_help=False)
    parent.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks instead of one-line errors"
    )
    if not threads:  # a subcommand with a --threads of its own (sweep: threads per run)
        return parent
    parent.add_argument(
        "--threads",
        type=positive_int_arg,
        default=argparse.SUPPRESS,
        help="torch threads (default: OMP_NUM_THREADS if set, else the cores other processes leave free now)",
    )
    return parent


def finish_namespace(args: argparse.Namespace) -> argparse.Namespace:
    """Fill the global options a subcommand did not set (``SUPPRESS`` keeps subparsers from resetting them)."""
    for name, default in (("debug", False), ("threads", None)):
        if not hasattr(args, name):
            setattr(args, name, default)
    return args


def default(cls: Any, name: str) -> Any:
    """The default of dataclass field ``name`` (the one source the CLI reads, never repeats)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            if f.default is not dataclasses.MISSING:
                return f.default
            if f.default_factory is not dataclasses.MISSING:
                return f.default_factory()
            raise ValueError(f"{cls.__name__}.{name} has no default")
    raise ValueError(f"{cls.__name__} has no field {name!r}")


def add_subparser(sub: Any, name: str, threads: bool = True, **kwargs: Any) -> argparse.ArgumentParser:
    """A subcommand parser that also takes the global options (``threads=False``: all but ``--threads``)."""
    return sub.add_parser(name, parents=[common_options(threads)], **kwargs)  # parser_class: OneLineParser


def signature_default(fn: Any, name: str) -> Any:
    """The default of keyword ``name`` of library function ``fn`` (for options that mirror one)."""
    return inspect.signature(fn).parameters[name].default
