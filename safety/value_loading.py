"""Loading any value function (our checkpoints, DeepReach state dicts, grid solutions) by path.

Everything in :mod:`safety` takes a :class:`~reach.value_function.ValueFunction`;
this module turns what users have on disk into one (the one call the rollout engine and the filter
need per step, ``value_and_gradient``, lives with the interface in :mod:`reach.value_function`).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch

from groundtruth.pairwise import PairwiseUnion
from groundtruth.solution import GridSolution
from reach.systems import ControlAffineSystem, MultiVehicle, RelativePair, make_system
from reach.validation import check_input_file
from reach.value_function import MinimumOf, ValueFunction
from training import pretrained
from training.checkpoint import load_network
from training.deepreach import load_deepreach
from training.network import NeuralValueFunction

Format = Literal["auto", "reach", "deepreach", "grid"]
FORMATS = ("auto", "reach", "deepreach", "grid")
#: ``"min:A,B"``: the pointwise minimum of sources A and B (:class:`~reach.value_function.MinimumOf`)
MIN_PREFIX = "min:"
#: ``"cap:A,B"``: the same minimum, steered by A's gradient everywhere (``MinimumOf(..., steer_by=0)``)
CAP_PREFIX = "cap:"


@dataclass
class LoadedValueFunction:
    """A value function with where it came from (for tables and error messages)."""

    value_function: ValueFunction
    path: Path
    kind: str  # "reach" | "deepreach" | "grid" | "pairwise"
    layout: str  # activation layout, or "grid"
    label: str


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """A run directory means its ``checkpoint.pt``, ``"pretrained:NAME"`` the shipped model's file
    (:mod:`training.pretrained`); files are returned as they are."""
    if pretrained.is_pretrained(path):
        return pretrained.checkpoint_path(str(path))
    p = Path(path)
    if p.is_symlink() and not p.exists():
        raise ValueError(f"{p}: a broken symbolic link or a link loop")
    if p.is_dir():
        ckpt = p / "checkpoint.pt"
        if not ckpt.exists():
            raise ValueError(f"{p}: a directory without checkpoint.pt is not a training run")
        return check_input_file(ckpt, "value-function source")
    if not p.exists():
        raise ValueError(f"{p}: no such file or directory")
    return check_input_file(p, "value-function source")


def detect_format(path: Path) -> str:
    """``grid`` for ``.npz``, ``deepreach`` for ``.pth``, ``reach`` otherwise (``.pt``, run dirs)."""
    if path.suffix == ".npz":
        return "grid"
    if path.suffix == ".pth":
        return "deepreach"
    return "reach"


def as_value_function(
    source: ValueFunction | str | os.PathLike,
    system: ControlAffineSystem | str | None = None,
    device: str | torch.device = "cpu",
    what: str = "value function",
) -> ValueFunction:
    """A value function from a path (see :func:`load_value_function`) or as given, checked against
    ``system`` by the one compatibility rule (:meth:`~reach.systems.base.ControlAffineSystem.same_physics`).

    The filters, their env wrappers and the plots take either form through this function."""
    if isinstance(source, (str, os.PathLike)):
        return load_value_function(source, system=system, device=device).value_function
    if not isinstance(source, ValueFunction):
        raise ValueError(f"expected a ValueFunction or a path, got {type(source).__name__}")
    if system is not None:
        wanted = make_system(system)
        wanted.require_same_physics(source.system, what)
    return source


def load_value_function(
    path: str | os.PathLike,
    format: Format = "auto",
    system: ControlAffineSystem | str | None = None,
    layout: str | None = None,
    device: str | torch.device = "cpu",
    label: str | None = None,
) -> LoadedValueFunction:
    """Load a value function from disk; mismatches and corrupt files raise ``ValueError``.

    Args:
        path: a run directory, a checkpoint ``.pt``, a DeepReach ``.pth``, a grid ``.npz`` or a
            shipped model, ``"pretrained:NAME"`` (``reach pretrained`` lists them).
        format: ``auto`` guesses from the suffix (see :func:`detect_format`).
        system: the expected system (required for DeepReach files, which do not store it); a
            stored system with the same physics (:meth:`physics_config`: horizon and sampling box
            may differ) is accepted.
        layout: the expected layout (required for DeepReach files).
        device: where a network's weights go (grid tables follow the states' device).

    A grid solution of a :class:`RelativePair` loaded for a multi-vehicle ``system`` becomes the
    union of pairwise BRTs (:class:`~groundtruth.pairwise.PairwiseUnion`, kind ``"pairwise"``).

    ``"min:A,B,..."`` loads the pointwise minimum of the sources (:class:`~reach.value_function.MinimumOf`,
    kind ``"min"``): ``A`` as asked, the others for ``A``'s system, so ``"min:RUN,pair.npz"`` caps a
    9D network with the union of pairwise BRTs, an upper bound on the cooperative value; its policy
    follows whichever member is smaller. ``"cap:A,B,..."`` is the same minimum steered by ``A``'s
    gradient everywhere (kind ``"cap"``): the value is capped, the policy stays the network's.
    Grid solutions load with ``outside="clamp"``: states that leave the grid (which closed-loop
    rollouts and episodes do) get the nearest edge value instead of an error.
    """
    if format not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {format!r}")
    if system is not None:
        system = make_system(system)  # an instance, a registered name or an import path
    if is_composition(path):
        return _load_minimum(str(path), format, system, layout, device, label)
    p = resolve_checkpoint(path)
    if pretrained.is_pretrained(path):  # a shipped network (.pt) or grid (.npz), by its card's format
        format, label = detect_format(p), label or str(path)
    try:
        return _load(p, format, system, layout, device, label)
    except (OSError, EOFError, KeyError, TypeError, RuntimeError, zipfile.BadZipFile) as err:
        # whatever a damaged or foreign file raises, the caller gets one ValueError naming the file
        raise ValueError(f"{p}: cannot be loaded as a value function ({type(err).__name__}: {err})") from err


def composition_kind(spec: object) -> str | None:
    """``"min"`` for a ``"min:A,B,..."`` source, ``"cap"`` for a ``"cap:A,B,..."`` one, else None."""
    text = str(spec)
    return "min" if text.startswith(MIN_PREFIX) else "cap" if text.startswith(CAP_PREFIX) else None


def is_composition(spec: object) -> bool:
    """Whether ``spec`` is a ``"min:A,B,..."`` or ``"cap:A,B,..."`` source."""
    return composition_kind(spec) is not None


def min_sources(spec: str) -> list[str]:
    """The member sources of a ``"min:A,B,..."`` or ``"cap:A,B,..."`` source."""
    prefix = CAP_PREFIX if composition_kind(spec) == "cap" else MIN_PREFIX
    return [part.strip() for part in spec[len(prefix) :].split(",") if part.strip()]


def member_sources(spec: str) -> list[str]:
    """The sources a source is made of: the members of a ``"min:"``/``"cap:"`` one, else itself."""
    return min_sources(spec) if is_composition(spec) else [spec]


def _load_minimum(
    spec: str,
    format: Format,
    system: ControlAffineSystem | None,
    layout: str | None,
    device: str | torch.device,
    label: str | None,
) -> LoadedValueFunction:
    kind = composition_kind(spec)
    parts = min_sources(spec)
    if len(parts) < 2:
        raise ValueError(f"{spec!r}: a minimum needs at least two sources, '{kind}:A,B'")
    if any(is_composition(part) for part in parts):
        raise ValueError(f"{spec!r}: minimums do not nest")
    first = load_value_function(parts[0], format=format, system=system, layout=layout, device=device)
    rest = [load_value_function(part, system=first.value_function.system, device=device) for part in parts[1:]]
    members = [first, *rest]
    labels = tuple(m.label for m in members)
    vf = MinimumOf(*(m.value_function for m in members), labels=labels, steer_by=0 if kind == "cap" else None)
    name = label or f"{kind}({', '.join(labels)})"
    return LoadedValueFunction(vf, first.path, kind, first.layout, name)


def _load(
    p: Path,
    format: Format,
    system: ControlAffineSystem | None,
    layout: str | None,
    device: str | torch.device,
    label: str | None,
) -> LoadedValueFunction:
    kind = detect_format(p) if format == "auto" else format
    name = label or (p.parent.name if p.name == "checkpoint.pt" else p.stem)
    if kind == "grid":
        # closed-loop states drift off the grid (cars leave the box): use the nearest edge value there
        sol = GridSolution.load(p, outside="clamp")
        if isinstance(sol.system, RelativePair) and isinstance(system, MultiVehicle):
            # a two-car solution evaluated on a multi-vehicle state: the union of pairwise BRTs
            return LoadedValueFunction(PairwiseUnion(system, sol), p, "pairwise", "pairwise union", name)
        if system is not None:
            system.require_same_physics(sol.system, f"{p}: grid solution")
        return LoadedValueFunction(sol, p, "grid", "grid", name)
    if kind == "deepreach":
        if system is None or layout is None:
            raise ValueError(f"{p}: a DeepReach state dict stores neither system nor layout; give both")
        net = load_deepreach(p, system, layout).to(device)
        return LoadedValueFunction(NeuralValueFunction(net), p, "deepreach", layout, name)
    net = load_network(p, system=system, layout=layout, device=device)
    return LoadedValueFunction(NeuralValueFunction(net), p, "reach", net.layout, name)
