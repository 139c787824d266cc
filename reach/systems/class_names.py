"""How configs name a system class, kept apart from the registry so that the base class imports it without a loop.

:meth:`ControlAffineSystem.reference` needs this, and :mod:`reach.systems.registry` needs the base
class: keeping the names table here lets ``base`` import it without importing the registry (no import
loop). The registry fills :data:`SYSTEMS` and re-exports everything below.
"""

from __future__ import annotations

#: System classes (``ControlAffineSystem`` subclasses) by registry key
#: (:func:`reach.systems.registry.registry_key`); :func:`reach.systems.registry.register_system` fills it.
SYSTEMS: dict[str, type] = {}


def import_path(cls: type) -> str:
    """``module:QualName`` of a class."""
    return f"{cls.__module__}:{cls.__qualname__}"


def system_reference(cls: type) -> str:
    """What configs store for ``cls``: the registered name of a built-in system, else the import path.

    A user's registered name is known only in processes that imported its module, while the import
    path lets a fresh process find the class (see :mod:`reach.systems.registry` for when it is imported)."""
    key = cls.__dict__.get("_registered_as")
    builtin = cls.__module__.split(".")[0] == "reach"
    return key if builtin and key is not None and SYSTEMS.get(key) is cls else import_path(cls)
