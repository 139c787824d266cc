"""Checkpoints: a state dict plus JSON metadata, written atomically, validated when loaded."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from reach.atomic import atomic_path
from reach.provenance import package_versions
from reach.systems import ControlAffineSystem, system_from_config
from training.network import Encoding, ValueNetwork

FORMAT = "reach.checkpoint.v1"


def save_checkpoint(
    path: str | os.PathLike,
    network: ValueNetwork,
    extra: dict[str, Any] | None = None,
    metadata: dict[str, Any] | None = None,
) -> None:
    """Write ``path`` (torch) and ``path.with_suffix('.json')`` (metadata), each atomically.

    ``extra`` holds training state (optimizer, RNG, step) for resuming; ``metadata`` is merged into
    the JSON beside the network's architecture and package versions.
    """
    path = Path(path)
    meta = {"format": FORMAT, **network.architecture(), "versions": package_versions(), **(metadata or {})}
    payload = {"format": FORMAT, "metadata": meta, "model": network.state_dict(), **(extra or {})}
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    with atomic_path(path.with_suffix(".json")) as tmp, open(tmp, "w") as fh:
        json.dump(meta, fh, indent=2, sort_keys=True)


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """The raw checkpoint dict; unreadable or foreign files raise ``ValueError``."""
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:
        raise ValueError(f"{path}: corrupt or unreadable checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path}: not a reach checkpoint (format {FORMAT!r} expected)")
    return payload


def load_network(
    path: str | os.PathLike,
    system: ControlAffineSystem | None = None,
    layout: str | None = None,
    device: str | torch.device = "cpu",
) -> ValueNetwork:
    """Rebuild the network of a checkpoint; a different ``system`` or ``layout`` than expected,
    weights that do not fit, or NaN/inf weights raise ``ValueError`` saying what does not match."""
    payload = read_checkpoint(path)
    meta = payload["metadata"]
    stored = system_from_config(meta["system"])
    if system is not None and stored != system:
        raise ValueError(f"{path}: checkpoint is for system {stored.config()}, not {system.config()}")
    if layout is not None and meta["layout"] != layout:
        raise ValueError(f"{path}: checkpoint has layout {meta['layout']!r}, not {layout!r}")
    net = ValueNetwork(
        stored,
        meta["layout"],
        width=meta["width"],
        parameterisation=meta["parameterisation"],
        w0=meta["w0"],
        encoding=Encoding.from_dict(meta["encoding"]),
    )
    state = payload["model"]
    for name, tensor in state.items():
        if torch.is_tensor(tensor) and tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise ValueError(f"{path}: weight {name} contains NaN or inf; refusing to load")
    try:
        net.load_state_dict(state)
    except RuntimeError as err:
        raise ValueError(
            f"{path}: weights do not match layout {meta['layout']!r} width {meta['width']}: {err}"
        ) from err
    return net.to(device)
