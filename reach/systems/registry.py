"""Finding a system by name, by import path or as given: one resolver for every tool.

A system can be referred to in three ways, everywhere a system is accepted (Python calls, configs,
checkpoints, ``.npz`` files, the CLI's ``--system``):

* an instance of :class:`~reach.systems.base.ControlAffineSystem` (or its class);
* a **registered name**: the built-ins (``air3d``, ``multivehicle9d``, ...) and any class decorated
  with :func:`register_system`; names are case-insensitive and ignore ``-`` and ``_``;
* an **import path** ``package.module:ClassName``, for a class in an importable module.

What a run stores (:meth:`ControlAffineSystem.config`) is the registered name of a built-in system
and the import path of any other, so a saved run reloads in a fresh process.

**Import paths read from files are not imported blindly.** Importing a module runs its code, and a
checkpoint or ``.npz`` from elsewhere must not choose which code runs (the same rule as
``torch.load(weights_only=True)``). :func:`system_from_config` therefore resolves a stored import
path only when its module is already imported, is registered, or is trusted: named by the caller
(``make_system("pkg.mod:Cls")``, the CLI's ``--system pkg.mod:Cls``), added with
:func:`trust_module`, or listed in the ``REACH_TRUSTED_MODULES`` environment variable (comma-separated
module prefixes). Otherwise the error names the path and says how to trust it.
"""

from __future__ import annotations

import importlib
import os
import sys
from typing import Any, TypeVar

from reach.systems.base import ControlAffineSystem

# the names table and the naming rule live in reach.systems.class_names (the base class needs them
# without importing this module); they are part of the registry's interface, re-exported here
from reach.systems.class_names import SYSTEMS, import_path, system_reference

__all__ = [
    "SYSTEMS",
    "SystemSpecified",
    "import_object",
    "import_path",
    "make_system",
    "register_system",
    "registry_key",
    "system_class",
    "system_from_config",
    "system_reference",
    "trust_module",
]

#: Module prefixes whose import paths may be imported when a file names them.
_TRUSTED: set[str] = set()

S = TypeVar("S", bound=type[ControlAffineSystem])


def registry_key(name: str) -> str:
    """The registry's spelling of ``name``: lower case without ``-`` and ``_``."""
    return name.lower().replace("-", "").replace("_", "")


def register_system(cls: S | None = None, *, name: str | None = None) -> Any:
    """Add a system class to the registry; usable as ``@register_system`` or ``@register_system(name=...)``.

    The name defaults to the class's ``name`` attribute (itself defaulting to the class name in lower
    case). Registering another class under a taken name raises ``ValueError``; registering the same
    class again (a module imported twice) is allowed.
    """

    def add(klass: S) -> S:
        if not (isinstance(klass, type) and issubclass(klass, ControlAffineSystem)):
            raise TypeError(f"register_system: expected a ControlAffineSystem subclass, got {klass!r}")
        key = registry_key(name or klass.name)
        if not key or ":" in key or not key.replace(".", "").isalnum():
            raise ValueError(f"register_system: name {name or klass.name!r} must be letters and digits")
        taken = SYSTEMS.get(key)
        if taken is not None and import_path(taken) != import_path(klass):
            raise ValueError(f"register_system: name {key!r} is taken by {import_path(taken)}")
        klass.name = key
        klass._registered_as = key
        SYSTEMS[key] = klass
        return klass

    return add if cls is None else add(cls)


def trust_module(*prefixes: str) -> None:
    """Allow files (checkpoints, ``.npz``, run configs) to name systems from these modules."""
    for prefix in prefixes:
        if not prefix or not all(part.isidentifier() for part in prefix.split(".")):
            raise ValueError(f"trust_module: {prefix!r} is not a module name")
        _TRUSTED.add(prefix)


def _trusted(module: str) -> bool:
    env = {p.strip() for p in os.environ.get("REACH_TRUSTED_MODULES", "").split(",") if p.strip()}
    return any(module == p or module.startswith(p + ".") for p in _TRUSTED | env)


def import_object(path: str, *, what: str = "object", from_file: bool = False) -> Any:
    """The object at ``package.module:QualName`` (``ValueError`` naming the path if there is none).

    With ``from_file`` (the path was read from a file), a module not yet imported is imported only if
    it is trusted (see the module docstring)."""
    module_name, _, qualname = path.partition(":")
    if not module_name or not qualname or not all(p.isidentifier() for p in module_name.split(".")):
        raise ValueError(f"{what} {path!r}: an import path looks like 'package.module:Name'")
    if module_name not in sys.modules:
        if from_file and not _trusted(module_name):
            raise ValueError(
                f"{what} {path!r} is named by a file, and importing {module_name!r} would run its code: "
                f"import it first, pass --system {path} (Python: make_system({path!r})), "
                f"or trust it with REACH_TRUSTED_MODULES={module_name}"
            )
        if module_name == "__main__":
            raise ValueError(f"{what} {path!r} was defined in a script's __main__: move it to an importable module")
        try:
            importlib.import_module(module_name)
        except ImportError as err:
            raise ValueError(f"{what} {path!r}: cannot import module {module_name!r} ({err})") from None
    obj: Any = sys.modules[module_name]
    for part in qualname.split("."):
        if part == "<locals>" or not hasattr(obj, part):
            raise ValueError(
                f"{what} {path!r}: module {module_name!r} has no {qualname!r} "
                "(what is defined inside a function cannot be found by path)"
            )
        obj = getattr(obj, part)
    return obj


def _class_from_path(path: str, *, from_file: bool) -> type[ControlAffineSystem]:
    obj = import_object(path, what="system", from_file=from_file)
    if not (isinstance(obj, type) and issubclass(obj, ControlAffineSystem)):
        raise ValueError(f"system {path!r} is not a ControlAffineSystem subclass")
    return obj


def system_class(reference: str, *, from_file: bool = False) -> type[ControlAffineSystem]:
    """The class a registered name or an import path refers to (``ValueError`` naming it if none)."""
    if not isinstance(reference, str):
        raise ValueError(f"a system reference must be a name or an import path, got {reference!r}")
    if ":" in reference:
        return _class_from_path(reference, from_file=from_file)
    key = registry_key(reference)
    if key not in SYSTEMS:
        raise ValueError(
            f"unknown system {reference!r}; registered systems: {sorted(SYSTEMS)} "
            "(or give an import path, package.module:ClassName)"
        )
    return SYSTEMS[key]


def make_system(system: Any, **parameters: Any) -> ControlAffineSystem:
    """A system from an instance, a class, a registered name or an import path.

    ``make_system("multivehicle9d")``, ``make_system("my_pkg.dynamics:DubinsAvoid", radius=0.5)``,
    ``make_system(DubinsAvoid())``. Parameters go to the class's constructor; an instance takes none.
    """
    if isinstance(system, ControlAffineSystem):
        if parameters:
            raise ValueError(f"system parameters {parameters} given with a system instance {system!r}")
        return system
    cls = system if isinstance(system, type) and issubclass(system, ControlAffineSystem) else system_class(system)
    try:
        return cls(**parameters)
    except TypeError as err:  # unknown or missing parameters
        raise ValueError(f"system {system_reference(cls)!r}: bad parameters {parameters} ({err})") from None


def system_from_config(config: dict[str, Any]) -> ControlAffineSystem:
    """Inverse of :meth:`ControlAffineSystem.config` for configs read from files (see the module
    docstring for when an import path is imported)."""
    if not isinstance(config, dict) or not isinstance(config.get("name"), str):
        raise ValueError(f"a system config needs a 'name' key, got {config!r}")
    parameters = config.get("parameters", {})
    if not isinstance(parameters, dict):
        raise ValueError(f"system {config['name']!r}: parameters must be a mapping, got {parameters!r}")
    return make_system(system_class(config["name"], from_file=True), **parameters)


class SystemSpecified:
    """For configs with ``system`` and ``system_parameters`` fields, stored as JSON.

    ``system`` may be given as an instance (or a class): :meth:`take_system_instance` (called from
    the dataclass's ``__post_init__``) stores its reference and parameters in the two fields and
    keeps the instance, which :meth:`build_system` returns while the fields still describe it.
    """

    system: Any
    system_parameters: dict[str, Any]

    def take_system_instance(self) -> None:
        if isinstance(self.system, type) and issubclass(self.system, ControlAffineSystem):
            self.system = make_system(self.system, **self.system_parameters)
        if isinstance(self.system, ControlAffineSystem):
            if self.system_parameters and self.system_parameters != self.system.parameters():
                raise ValueError(
                    f"system_parameters {self.system_parameters} given with a system instance {self.system!r}"
                )
            instance = self.system
            self.system, self.system_parameters = instance.reference(), dict(instance.parameters())
            self.__dict__["_system_instance"] = instance
        elif not isinstance(self.system, str):
            raise ValueError(f"system must be a name, an import path or a ControlAffineSystem, got {self.system!r}")

    def build_system(self) -> ControlAffineSystem:
        """The configured system (the instance given, while ``system`` and ``system_parameters`` still
        describe it; else built from them)."""
        instance = self.__dict__.get("_system_instance")
        if instance is not None and (instance.reference(), instance.parameters()) == (
            self.system,
            self.system_parameters,
        ):
            return instance
        return make_system(self.system, **self.system_parameters)
