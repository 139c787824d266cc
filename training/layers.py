"""The layers a value network is built of: layout letters, activations and their initialisation.

A layout is a string with one letter per activated hidden layer and a final ``l`` (linear output):
``s`` sine ``sin(w0 z)``, ``r`` ReLU, ``t`` tanh (:func:`parse_layout`).

Initialisation per layer kind, chosen so that every pre-activation starts with a spread of order one
whatever mixes the layout has:

* sine, first layer: ``U(-1/fan_in, 1/fan_in)`` (SIREN), so ``w0 z`` spans about one period over
  the normalised input box;
* sine, later layers (also after a ReLU or tanh layer): ``U(-sqrt(6/fan_in)/w0, +sqrt(6/fan_in)/w0)``
  (SIREN). It assumes inputs of second moment about 1/2, which sine outputs have and Kaiming-
  initialised ReLU outputs roughly have too, so ``w0 z`` stays of order one after a ReLU layer;
* ReLU: Kaiming-normal (fan_in, ReLU gain), biases zero; tanh: Xavier-uniform, biases zero;
* the linear output after a sine layer uses the SIREN hidden rule (as DeepReach), after ReLU or tanh
  Kaiming-normal with linear gain.

Why a module of its own: :class:`~training.network.ValueNetwork` stacks these layers, and the
formal bounds (:mod:`safety.formal.bounds`) bound the same activations without the network's
encoding or output map.
"""

from __future__ import annotations

import math

import torch
from torch import nn

#: Activation letters and their names.
ACTIVATIONS = {"s": "sine", "r": "relu", "t": "tanh"}


def parse_layout(layout: str) -> tuple[str, ...]:
    """Letters of the activated layers of ``layout``; errors name the bad part."""
    if not isinstance(layout, str) or not layout:
        raise ValueError(f"layout must be a non-empty string such as 'ssrsl', got {layout!r}")
    if not layout.endswith("l"):
        raise ValueError(f"layout {layout!r} must end with 'l' (the linear output layer)")
    body = layout[:-1]
    if not body:
        raise ValueError(f"layout {layout!r} needs at least one activated layer before the final 'l'")
    for i, letter in enumerate(body):
        if letter not in ACTIVATIONS:
            known = ", ".join(f"{k} = {v}" for k, v in ACTIVATIONS.items())
            raise ValueError(
                f"layout {layout!r}: unknown letter {letter!r} at position {i} (known: {known}, l = output)"
            )
    return tuple(body)


class Sine(nn.Module):
    """``sin(w0 z)``, the SIREN activation (layout letter ``s``)."""

    def __init__(self, w0: float) -> None:
        super().__init__()
        self.w0 = w0

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return torch.sin(self.w0 * z)

    def forward_(self, z: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` in ``z``'s own memory: the same values, no new tensor (inference only)."""
        return z.mul_(self.w0).sin_()

    def extra_repr(self) -> str:
        return f"w0={self.w0}"


def activate_in_place(activation: nn.Module, z: torch.Tensor) -> torch.Tensor:
    """``activation(z)`` written into ``z`` (which the caller owns and no graph records): the same
    values as the module's forward, without allocating a second activation-sized tensor."""
    if isinstance(activation, Sine):
        return activation.forward_(z)
    if isinstance(activation, nn.ReLU):
        return z.relu_()
    if isinstance(activation, nn.Tanh):
        return z.tanh_()
    return activation(z)


def make_activation(letter: str, w0: float) -> nn.Module:
    """The activation module of layout letter ``letter`` (``w0``: a sine layer's frequency)."""
    return {"s": lambda: Sine(w0), "r": nn.ReLU, "t": nn.Tanh}[letter]()


@torch.no_grad()
def init_linear(layer: nn.Linear, kind: str, previous: str | None, w0: float) -> None:
    """Initialise ``layer`` whose output feeds activation ``kind`` (``"l"`` for the output)."""
    fan_in = layer.in_features
    if kind == "s" or (kind == "l" and previous == "s"):
        bound = 1.0 / fan_in if previous is None else math.sqrt(6.0 / fan_in) / w0
        layer.weight.uniform_(-bound, bound)
        return  # biases keep torch's default init, as SIREN and DeepReach do
    if kind == "r":
        nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
    elif kind == "t":
        nn.init.xavier_uniform_(layer.weight, gain=nn.init.calculate_gain("tanh"))
    else:  # linear output after relu/tanh
        nn.init.kaiming_normal_(layer.weight, nonlinearity="linear")
    nn.init.zeros_(layer.bias)
