"""Checkpoints: a state dict plus JSON metadata, written atomically, validated when loaded.

Loading runs no code: files are read with ``torch.load(weights_only=True)``, which accepts tensors
and plain containers only, so a crafted pickle is refused instead of executed. Every checkpoint
carries a SHA-256 digest of its architecture and weights; a file whose metadata (say, its layout)
or weights were altered after saving fails the check instead of loading with wrong activations.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

import torch
from torch.torch_version import TorchVersion

from reach.atomic import atomic_path
from reach.provenance import package_versions
from reach.systems import ControlAffineSystem, system_from_config
from reach.validation import check_input_file
from training.encoding import Encoding
from training.network import ValueNetwork

FORMAT = "reach.checkpoint.v1"

#: the metadata that rebuilds a network (:meth:`ValueNetwork.architecture`), covered by the digest
ARCHITECTURE_KEYS = ("system", "layout", "width", "parameterisation", "w0", "encoding")


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
    architecture = network.architecture()
    clash = sorted(set(metadata or {}) & {*architecture, "format", "integrity"})
    if clash:
        raise ValueError(f"metadata may not override the network's own fields {clash}")
    state = network.state_dict()
    meta = {
        "format": FORMAT,
        **architecture,
        "versions": package_versions(),
        **(metadata or {}),
        "integrity": {"sha256": _digest(architecture, state)},
    }
    payload = {"format": FORMAT, "metadata": meta, "model": state, **(extra or {})}
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    with atomic_path(path.with_suffix(".json")) as tmp, open(tmp, "w") as fh:
        json.dump(meta, fh, indent=2, sort_keys=True)


def network_digest(network: torch.nn.Module) -> str:
    """The fingerprint of a value network: the SHA-256 its checkpoint records (architecture and weights)."""
    return _digest(network.architecture(), network.state_dict())


def _digest(architecture: dict[str, Any], state: dict[str, torch.Tensor]) -> str:
    """SHA-256 over the architecture (canonical JSON) and every tensor's name, dtype, shape and bytes."""
    h = hashlib.sha256(json.dumps(architecture, sort_keys=True).encode())
    for name in sorted(state):
        tensor = state[name].detach().cpu().contiguous()
        h.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        h.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return h.hexdigest()


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """The raw checkpoint dict, loaded without running code (``weights_only=True``); unreadable,
    foreign or code-carrying files raise ``ValueError``."""
    check_input_file(path, "checkpoint")
    try:
        # TorchVersion (a str subclass) is in the metadata of checkpoints written before 0.1.1
        with torch.serialization.safe_globals([TorchVersion]):
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        found = re.search(r"(?:unsupported|Unsupported global:) GLOBAL ([\w.]+)", str(err))
        if found:
            name = found.group(1)
            raise ValueError(
                f"{path}: holds a Python object ({name}) that loading would have to run; a reach "
                "checkpoint holds only tensors and plain data, so it was not loaded"
            ) from err
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise ValueError(f"{path}: corrupt or unreadable checkpoint ({type(err).__name__}: {first[:200]})") from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path}: not a reach checkpoint (format {FORMAT!r} expected)")
    meta = payload.get("metadata")
    if not isinstance(meta, dict) or not isinstance(payload.get("model"), dict):
        raise ValueError(f"{path}: checkpoint without metadata or weights")
    missing = [key for key in ARCHITECTURE_KEYS if key not in meta]
    if missing:
        raise ValueError(f"{path}: checkpoint metadata lacks {missing}")
    return payload


def check_integrity(path: str | os.PathLike, payload: dict[str, Any]) -> None:
    """Refuse a checkpoint whose stored digest is missing or does not match its architecture and
    weights: a digest deleted along with an edit must not let the edit load."""
    meta = payload["metadata"]
    integrity = meta.get("integrity")
    stored = integrity.get("sha256") if isinstance(integrity, dict) else None
    if not isinstance(stored, str):
        raise ValueError(
            f"{path}: checkpoint metadata has no integrity digest (field 'integrity.sha256'), which every "
            "reach checkpoint carries; its metadata or weights may have been edited, so it was not loaded"
        )
    architecture = {k: meta[k] for k in ARCHITECTURE_KEYS}
    if _digest(architecture, payload["model"]) != stored:
        raise ValueError(
            f"{path}: metadata or weights were changed after saving (digest mismatch; layout "
            f"{meta.get('layout')!r}); refusing to load"
        )


def load_network(
    path: str | os.PathLike,
    system: ControlAffineSystem | None = None,
    layout: str | None = None,
    device: str | torch.device = "cpu",
) -> ValueNetwork:
    """Rebuild the network of a checkpoint; a different ``system`` or ``layout`` than expected,
    weights that do not fit, or NaN/inf weights raise ``ValueError`` saying what does not match."""
    return network_from_payload(path, read_checkpoint(path), system, layout, device)


def network_from_payload(
    path: str | os.PathLike,
    payload: dict[str, Any],
    system: ControlAffineSystem | None = None,
    layout: str | None = None,
    device: str | torch.device = "cpu",
) -> ValueNetwork:
    """:func:`load_network` for a checkpoint already read by :func:`read_checkpoint` (a resumed run
    needs the optimizer and RNG state of the same file too); ``path`` names it in errors."""
    check_integrity(path, payload)
    meta = payload["metadata"]
    stored = system_from_config(meta["system"])
    if system is not None:
        system.require_same_physics(stored, f"{path}: checkpoint")
    if layout is not None and meta["layout"] != layout:
        raise ValueError(f"{path}: checkpoint has layout {meta['layout']!r}, not {layout!r}")
    try:
        net = ValueNetwork(
            stored,
            meta["layout"],
            width=meta["width"],
            parameterisation=meta["parameterisation"],
            w0=meta["w0"],
            encoding=Encoding.from_dict(meta["encoding"]),
        )
    except (TypeError, KeyError) as err:
        raise ValueError(f"{path}: checkpoint metadata does not describe a network ({err})") from err
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
