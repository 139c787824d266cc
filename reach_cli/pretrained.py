"""``reach pretrained``: the value networks shipped with the package, with their model cards."""

from __future__ import annotations

import argparse
import json
from typing import Any

from reach_cli.options import add_subparser
from training import pretrained


def add_parser(sub: Any) -> None:
    p = add_subparser(
        sub,
        "pretrained",
        help="list the shipped value networks (use them as pretrained:NAME) with their model cards",
    )
    p.add_argument("names", nargs="*", help="show only these models")
    p.add_argument("--json", action="store_true", help="print the full cards as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    shown = [pretrained.card(name) for name in args.names] if args.names else pretrained.cards()
    if args.json:
        print(json.dumps([c.to_dict() for c in shown], indent=2))
        return 0
    if not shown:
        print("no pretrained models are installed")
        return 0
    print("\n\n".join(c.describe() for c in shown))
    return 0
