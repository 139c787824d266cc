"""Import DeepReach checkpoints (state dicts with keys ``net.net.{i}.0.weight`` / ``.bias``).

DeepReach stores no layout: the caller names it (the seed authors encode it in file names). The
encoding is DeepReach's (raw t, headings / 1.2 pi, ``V = 25 o + 0.25``), the parameterisation
vanilla, the sine frequency 30.
"""

from __future__ import annotations

import os
import re

import torch

from reach.systems import ControlAffineSystem
from training.network import Encoding, ValueNetwork, parse_layout

_KEY = re.compile(r"^net\.net\.(\d+)\.0\.(weight|bias)$")


def load_deepreach(path: str | os.PathLike, system: ControlAffineSystem, layout: str = "ssssl") -> ValueNetwork:
    """A :class:`ValueNetwork` holding a DeepReach state dict; mismatches raise ``ValueError``."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise ValueError(f"{path}: not a readable torch state dict ({type(err).__name__}: {err})") from err
    if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
        state = state["model"]
    if not isinstance(state, dict) or not state:
        raise ValueError(f"{path}: expected a DeepReach state dict, got {type(state).__name__}")
    layers: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in state.items():
        m = _KEY.match(key)
        if not m:
            raise ValueError(
                f"{path}: unexpected key {key!r} for a DeepReach checkpoint (expected net.net.<i>.0.weight/bias)"
            )
        layers.setdefault(int(m.group(1)), {})[m.group(2)] = value
    letters = parse_layout(layout)
    if len(layers) != len(letters) + 1:
        raise ValueError(
            f"{path}: has {len(layers)} linear layers, layout {layout!r} needs {len(letters) + 1} "
            f"({len(letters)} activated + output)"
        )
    width = layers[0]["weight"].shape[0]
    net = ValueNetwork(
        system, layout, width=width, parameterisation="vanilla", w0=30.0, encoding=Encoding.deepreach(system)
    )
    targets = [*net.layers, net.output]
    for i, target in enumerate(targets):
        for name in ("weight", "bias"):
            src = layers[i].get(name)
            dst = getattr(target, name)
            if src is None or src.shape != dst.shape:
                got = None if src is None else tuple(src.shape)
                raise ValueError(
                    f"{path}: layer {i} {name} has shape {got}, but {system.name} with layout {layout!r} "
                    f"and width {width} needs {tuple(dst.shape)}"
                )
            if not torch.isfinite(src).all():
                raise ValueError(f"{path}: layer {i} {name} contains NaN or inf")
            with torch.no_grad():
                dst.copy_(src)
    return net
