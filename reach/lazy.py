"""Names a package exports but imports on first use, so that importing the package stays light.

A package whose ``__init__`` would otherwise load a heavy stack (Gymnasium for the env adapters, the
studies' plotting) lists those names with the module that defines each, and gets a module-level
``__getattr__`` and ``__dir__`` from :func:`lazy_exports`. The first lookup imports the module and
stores the name in the package, so later lookups cost nothing.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, table: dict[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package`` that import each name of ``table`` (name -> the
    module defining it) on first use; any other name raises ``AttributeError`` as usual."""
    namespace = sys.modules[package].__dict__

    def lookup(name: str) -> Any:
        module = table.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        namespace[name] = value  # later lookups skip this function
        return value

    def names() -> list[str]:
        return sorted({*namespace, *table})

    return lookup, names


__all__ = ["lazy_exports"]
