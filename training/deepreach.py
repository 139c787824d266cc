"""Import DeepReach checkpoints (state dicts with keys ``net.net.{i}.0.weight`` / ``.bias``).

DeepReach stores no layout: the caller names it (the seed authors encode it in file names). The
encoding is DeepReach's as the system declares it (:class:`~reach.systems.DeepReachNormalisation`:
raw t, states scaled by its mean and variance, headings / 1.2 pi), the sine frequency 30, and the
output either DeepReach 2021's vanilla ``V = 25 o + 0.25`` (the seed authors' Air3D and 9D
checkpoints) or the public release's ``diff_model``, ``V = b(x) + scale * o`` (every system of
its catalogue; the ``diff`` parameterisation). A system whose DeepReach network takes extra zero
inputs (``RocketLanding``) has those weight columns dropped on import: they multiply zeros.

Neither the layout nor the system can be read from the file, and a wrong guess of equal shapes
(``rrrrl`` weights loaded as ``ssssl``, Air3D weights loaded as another 3D system) would load
silently. So every import is checked against what any trained DeepReach model satisfies: the
boundary condition ``V(x, 0) = l(x)``. On uniform states the mean ``|V(x, 0) - l(x)|`` must stay
below :data:`BOUNDARY_TOLERANCE` of the mean ``|l(x)|``: the seed authors' Air3D model is at 0.014,
every wrong layout or system we tried at 0.40 or more.
"""

from __future__ import annotations

import os
import re

import torch

from reach.systems import ControlAffineSystem
from training.encoding import Encoding
from training.layers import parse_layout
from training.network import ValueNetwork

#: largest mean |V(x, 0) - l(x)| / mean |l(x)| accepted for an imported model
BOUNDARY_TOLERANCE = 0.2

_KEY = re.compile(r"^net\.net\.(\d+)\.0\.(weight|bias)$")


def load_deepreach(
    path: str | os.PathLike,
    system: ControlAffineSystem,
    layout: str = "ssssl",
    check_boundary: bool = True,
    model: str | None = None,
) -> ValueNetwork:
    """A :class:`ValueNetwork` holding a DeepReach state dict; mismatches raise ``ValueError``.

    ``model`` is ``"vanilla"`` or ``"diff"`` (DeepReach's ``diff_model``); ``None`` takes the one the
    system declares. ``check_boundary=False`` skips the ``V(x, 0) = b(x)`` check (see the module
    docstring), for a model that was never trained to its boundary condition."""
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
    encoding = Encoding.deepreach(system)  # refuses a system without a DeepReach normalisation, by name
    model = system.deepreach.model if model is None else model
    if model not in ("vanilla", "diff"):
        raise ValueError(f"model must be 'vanilla' or 'diff' (DeepReach's diff_model), got {model!r}")
    net = ValueNetwork(system, layout, width=width, parameterisation=model, w0=30.0, encoding=encoding)
    extra = system.deepreach.extra_inputs
    first = layers[0].get("weight")
    if extra and first is not None and first.ndim == 2 and first.shape[1] == net.layers[0].weight.shape[1] + extra:
        layers[0]["weight"] = first[:, : first.shape[1] - extra]  # the columns of DeepReach's zero inputs
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
    if check_boundary:
        check_boundary_condition(net, path, layout)
    return net


@torch.no_grad()
def check_boundary_condition(net: ValueNetwork, path: str | os.PathLike, layout: str, samples: int = 2000) -> float:
    """Raise unless ``V(x, 0)`` of ``net`` matches ``b(x)`` (``l``; ``max(l, -g)`` for reach-avoid; see the
    module docstring); returns the relative error."""
    system = net.system
    x = system.sample_states(samples, generator=torch.Generator().manual_seed(0), dtype=torch.float32)
    margin = system.boundary_value(x)
    value = net(x, torch.zeros(samples))
    error = float((value - margin).abs().mean() / margin.abs().mean().clamp_min(1e-12))
    if not error < BOUNDARY_TOLERANCE:  # NaN fails too
        raise ValueError(
            f"{path}: as {system.name} with layout {layout!r}, V(x, 0) is {error:.2f} (relative mean error) "
            f"away from the boundary value b(x) (a trained model is within {BOUNDARY_TOLERANCE}); wrong system or "
            "layout? (check_boundary=False loads it anyway)"
        )
    return error
