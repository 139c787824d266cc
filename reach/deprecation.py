"""Deprecation aliases: an import path that moved keeps working, with a warning, for one release.

A public module that moves leaves behind a one-line alias module at its old path that calls
:func:`moved` (or :func:`split`, for a module whose contents now live in several). A moved alias
*is* the new module (``sys.modules`` maps the old name to it), so ``from old.path import name``,
``import old.path`` and monkeypatching through the old path all reach the same objects. Aliases are
the only modules allowed to name a higher layer, and nothing in the library imports one
(``tests/test_layers.py`` holds both rules).
"""

from __future__ import annotations

import importlib
import sys
import warnings
from types import ModuleType

#: the release in which every alias listed in :data:`MOVED` is removed
REMOVED_IN = "0.3"

#: every moved public path and where it lives now (old -> new); the alias modules read it, and the
#: tests check each alias resolves to its target and warns
MOVED: dict[str, str] = {
    "reach.cli": "reach_cli",
    "reach.cli.common": "reach_cli.options",
    "safety.evaluate": "studies.batch_verification",
    "safety.filter_eval": "studies.filter_eval",
    "safety.plots": "studies.plots",
    "safety.demo": "studies.demo",
    "safety.results_io": "studies.tables",
    "safety.tasks": "studies.tasks",
    "safety.policy": "safety.value_policies",
    "safety.value_functions": "safety.sources",
    "sweeps": "studies.sweeps",
    "training.evaluate": "training.accuracy",
    "reach.systems.backend": "reach.systems.arrays",
}


#: modules split in two or more (old -> new ones); the alias holds every public name of each
SPLIT: dict[str, tuple[str, ...]] = {
    "reach_envs.common": ("reach_envs.spaces", "reach_envs.views"),
}


def moved(old: str, submodules: tuple[str, ...] = ()) -> ModuleType:
    """Make the module being imported as ``old`` an alias of its new home in :data:`MOVED`.

    Warns once per import with a :class:`DeprecationWarning` naming both paths. ``submodules``
    names the submodules of a moved package, so that ``import old.sub`` reaches ``new.sub`` too.
    """
    new = MOVED[old]
    warnings.warn(
        f"{old} moved to {new}; import it from there (the old path is removed in reach {REMOVED_IN})",
        DeprecationWarning,
        stacklevel=3,
    )
    module = importlib.import_module(new)
    sys.modules[old] = module
    for sub in submodules:
        sys.modules[f"{old}.{sub}"] = importlib.import_module(MOVED.get(f"{old}.{sub}", f"{new}.{sub}"))
    return module


def split(old: str) -> ModuleType:
    """Fill the module being imported as ``old`` with the public names of its parts in :data:`SPLIT`,
    warning with a :class:`DeprecationWarning` that names them."""
    parts = SPLIT[old]
    warnings.warn(
        f"{old} was split into {', '.join(parts)}; import from there (the old path is removed in reach {REMOVED_IN})",
        DeprecationWarning,
        stacklevel=3,
    )
    module = sys.modules[old]
    for part in parts:
        new = importlib.import_module(part)
        names = getattr(new, "__all__", [n for n in vars(new) if not n.startswith("_")])
        module.__dict__.update({name: getattr(new, name) for name in names})
    return module
