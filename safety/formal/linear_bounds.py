"""Linear bounds of a value network over boxes, propagated back through the layers (CROWN-style).

:mod:`safety.formal.bounds`' intervals forget how a layer's inputs are correlated, which on trained sine
networks costs three to four orders of magnitude. Here every activation is instead enclosed between
two parallel lines on its pre-activation interval (the chord's slope, each line's offset the
exact extreme of ``f(z) - slope z`` over the interval, found among the endpoints and the points where
``f'(z)`` equals the slope), and a bound of the output is carried back through the layers as one
linear function of the input with two constants. Pre-activation intervals, which the lines need,
are computed the same way layer by layer (each intersected with interval propagation's).

The heading encoding is the first layer: ``(t, x)`` maps linearly to ``(t', x_kept, theta, theta)``,
then elementwise to ``(t', x_kept, r sin theta, r cos theta)``, so sin and cos of the same heading
stay tied to it.

Same conventions as :mod:`safety.formal.bounds`: float64 on the CPU, boxes ``(B, n)``, times scalars or
``(B,)``, and an outward margin that bounds the float64 rounding of every product and sum (the
standard ``gamma_k = k u / (1 - k u)`` bound on a sum of products of ``k`` terms, applied to the
same computation in absolute values).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from safety.formal.bounds import FUNCTION_ULPS, UNIT_ROUNDOFF, Interval, check_box, interval_bounds, on_network_device
from training.layers import Sine
from training.network import ValueNetwork

__all__ = ["INTERMEDIATE", "linear_bounds"]

_TWO_PI = 2.0 * math.pi


@dataclass
class _Layer:
    """``z = W h + b`` followed by an elementwise function per unit (``kinds``: one name per unit, or one
    for all), times ``out_scale``."""

    weight: torch.Tensor  # (out, in)
    bias: torch.Tensor  # (out,)
    kinds: list[str]
    out_scale: torch.Tensor  # (out,)


def _function(kind: str, z: torch.Tensor) -> torch.Tensor:
    return {"id": lambda v: v, "sin": torch.sin, "cos": torch.cos, "tanh": torch.tanh, "relu": torch.relu}[kind](z)


def _critical_points(kind: str, slope: torch.Tensor, lo: torch.Tensor) -> list[torch.Tensor]:
    """Points where ``f'(z) = slope`` that may lie in ``[lo, lo + 2 pi]`` (more are never needed: wider
    intervals of sin and cos get the constant lines), or the kink of ReLU."""
    if kind in ("sin", "cos"):
        a = slope.clamp(-1.0, 1.0)
        # sin: cos z = a; cos: -sin z = a
        bases = [torch.arccos(a), -torch.arccos(a)] if kind == "sin" else [-torch.arcsin(a), math.pi + torch.arcsin(a)]
        points = []
        for base in bases:
            k = torch.floor((lo - base) / _TWO_PI)
            points += [base + (k + j) * _TWO_PI for j in range(3)]
        return points
    if kind == "tanh":  # 1 - tanh(z)^2 = a
        root = torch.atanh(torch.sqrt((1.0 - slope).clamp(0.0, 1.0 - 1e-16)))
        return [root, -root]
    if kind == "relu":
        return [torch.zeros_like(lo)]
    return []


def _relax(kind: str, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(slope, lower offset, upper offset)``: ``slope z + lower <= f(z) <= slope z + upper`` on ``[lo, hi]``."""
    if kind == "id":
        zero = torch.zeros_like(lo)
        return torch.ones_like(lo), zero, zero
    f_lo, f_hi = _function(kind, lo), _function(kind, hi)
    width = hi - lo
    slope = torch.where(width > 1e-12, (f_hi - f_lo) / width.clamp(min=1e-300), torch.zeros_like(lo))
    if kind in ("sin", "cos"):
        slope = torch.where(width >= _TWO_PI, torch.zeros_like(slope), slope)
    candidates = [lo, hi] + [torch.minimum(torch.maximum(p, lo), hi) for p in _critical_points(kind, slope, lo)]
    gaps = torch.stack([_function(kind, z) - slope * z for z in candidates])
    low, high = gaps.amin(0), gaps.amax(0)
    if kind in ("sin", "cos"):  # a whole period or more: the constant lines -1 and 1
        wide = width >= _TWO_PI
        low, high = torch.where(wide, -1.0, low), torch.where(wide, 1.0, high)
    # tiny intervals take slope 0: the offsets are then the function's own range, which the
    # candidates' extremes enclose only up to the function's curvature over the width
    tiny = width <= 1e-12
    low, high = torch.where(tiny, low - width, low), torch.where(tiny, high + width, high)
    scale = torch.maximum(lo.abs(), hi.abs())
    error = FUNCTION_ULPS * UNIT_ROUNDOFF * (1.0 + scale) * (2.0 + slope.abs())
    return slope, low - error, high + error


def _layers(network: ValueNetwork) -> tuple[list[_Layer], nn.Linear]:
    """The network as elementwise layers, the heading encoding first, plus its output layer."""
    enc = network.encoding
    n = network.system.state_dim
    angles = list(enc.sincos_dims)
    kept = [i for i in range(n) if i not in angles]
    scale = torch.tensor(enc.state_scale, dtype=torch.float64)
    offset = torch.tensor(enc.state_offset, dtype=torch.float64)
    units: list[tuple[torch.Tensor, float, str, float]] = []  # (row, bias, kind, output scale)

    def unit(column: int, weight: float, bias: float, kind: str = "id", radius: float = 1.0) -> None:
        row = torch.zeros(1 + n, dtype=torch.float64)
        row[column] = weight
        units.append((row, bias, kind, radius))

    unit(0, 1.0 / enc.time_scale, -enc.time_offset / enc.time_scale)
    for i in kept:
        unit(1 + i, 1.0 / float(scale[i]), float(-offset[i] / scale[i]))
    for kind in ("sin", "cos"):
        for i in angles:
            unit(1 + i, 1.0, 0.0, kind, enc.sincos_radius)
    rows, bias, kinds, out_scale = zip(*units)
    as_tensor = lambda values: torch.tensor(values, dtype=torch.float64)  # noqa: E731
    layers = [_Layer(torch.stack(rows), as_tensor(bias), list(kinds), as_tensor(out_scale))]
    for layer, act in zip(network.layers, network.activations):
        w = layer.weight.detach().to(torch.float64)
        b = layer.bias.detach().to(torch.float64)
        if isinstance(act, Sine):
            w, b, kind = w * act.w0, b * act.w0, "sin"
        elif isinstance(act, nn.ReLU):
            kind = "relu"
        elif isinstance(act, nn.Tanh):
            kind = "tanh"
        else:
            raise TypeError(f"no linear relaxation for activation {type(act).__name__}")
        layers.append(_Layer(w, b, [kind] * w.shape[0], torch.ones(w.shape[0], dtype=torch.float64)))
    return layers, network.output


def _relax_layer(layer: _Layer, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The layer's lines per unit, ``(B, out)`` each, with its output scale applied."""
    slope, low, high = torch.empty_like(lo), torch.empty_like(lo), torch.empty_like(lo)
    kinds = layer.kinds
    for kind in sorted(set(kinds)):
        cols = [j for j, k in enumerate(kinds) if k == kind]
        s, a, b = _relax(kind, lo[:, cols], hi[:, cols])
        slope[:, cols], low[:, cols], high[:, cols] = s, a, b
    r = layer.out_scale
    return slope * r, low * r, high * r  # r > 0


def _back_substitute(
    spec_w: torch.Tensor,
    spec_b: torch.Tensor,
    layers: list[_Layer],
    lines: list[tuple],
    inputs: Interval,
    magnitude: torch.Tensor,
) -> Interval:
    """Bounds of ``spec_w @ h + spec_b`` (``spec_w`` ``(B, m, width)``) where ``h`` is the output of
    ``layers`` (whose activations are enclosed by ``lines``) at inputs in the box ``inputs``.
    ``magnitude`` (``(B, width)``, :func:`_magnitudes`) bounds ``|h|`` and every partial sum that
    makes it, so ``|spec_w| magnitude`` bounds the sum of the absolute values of all the products
    computed here: the rounding margin."""
    lam = spec_w
    lower = spec_b.expand(lam.shape[:2]).clone()
    upper = lower.clone()
    depth = 0
    for layer, (slope, low, high) in zip(reversed(layers), reversed(lines)):
        mid, rad = 0.5 * (low + high), 0.5 * (high - low)
        centre = (lam @ mid.unsqueeze(-1)).squeeze(-1)
        spread = (lam.abs() @ rad.unsqueeze(-1)).squeeze(-1)
        lam = lam * slope.unsqueeze(1)
        shift = lam @ layer.bias
        lower, upper = lower + centre - spread + shift, upper + centre + spread + shift
        lam = lam @ layer.weight
        depth += layer.weight.shape[0] + layer.weight.shape[1] + 8
    lo, hi = inputs
    centre, radius = (0.5 * (lo + hi)).unsqueeze(-1), (0.5 * (hi - lo)).unsqueeze(-1)
    mid = (lam @ centre).squeeze(-1)
    spread = (lam.abs() @ radius).squeeze(-1)
    k = depth + lo.shape[-1] + 8
    total = (spec_w.abs() @ magnitude.unsqueeze(-1)).squeeze(-1) + spec_b.abs()
    error = (k * UNIT_ROUNDOFF / (1 - k * UNIT_ROUNDOFF)) * 4 * total
    return lower + mid - spread - error, upper + mid + spread + error


def _magnitudes(layer: _Layer, lines: tuple, previous: torch.Tensor) -> torch.Tensor:
    """A bound of ``|h|`` after ``layer`` and of every partial sum toward it, from ``previous``'s:
    ``|slope| (|W| m + |b|) + max(|low|, |high|)``. Forward, once per layer and box."""
    slope, low, high = lines
    z = previous @ layer.weight.abs().T + layer.bias.abs()
    return slope.abs() * z + torch.maximum(low.abs(), high.abs()) + z


def _forward_pre_activations(layers: list[_Layer], inputs: Interval, magnitude: torch.Tensor) -> tuple[list, list]:
    """Every layer's lines, with each pre-activation interval from linear bounds carried *forward*.

    Each unit's output is kept between two affine functions of the input's offset from the box's
    centre, ``A_lo d + c_lo <= h <= A_hi d + c_hi`` (``A`` ``(B, width, d)``), and a linear layer maps
    them on by splitting its weights by sign. This costs ``O(width^2 d)`` a layer and box, against
    back-substitution's ``O(width^3)`` per layer and layer below, so it is far cheaper when the input
    dimension ``d`` (time and state) is small against the width. It is looser on wide boxes: the gap
    between the two functions grows through ``|W|`` at every layer (``benchmarks/bound_tightness.py``;
    measured: docs/results/certificates.md). Rounding: each interval is widened by the same a-priori bound
    as back-substitution's (``_magnitudes`` bounds the absolute values of every product on the way).
    Returns the lines and the magnitudes per layer."""
    lo, hi = inputs
    centre, radius = 0.5 * (lo + hi), 0.5 * (hi - lo)
    batch, d = centre.shape
    a_lo = torch.eye(d, dtype=centre.dtype, device=centre.device).expand(batch, d, d)
    a_hi, c_lo, c_hi = a_lo, centre, centre
    lines: list[tuple] = []
    magnitudes: list[torch.Tensor] = []
    depth = 0
    for layer in layers:
        w, b = layer.weight, layer.bias
        w_pos, w_neg = w.clamp(min=0.0), w.clamp(max=0.0)
        z_a_lo, z_a_hi = w_pos @ a_lo + w_neg @ a_hi, w_pos @ a_hi + w_neg @ a_lo
        z_c_lo = c_lo @ w_pos.T + c_hi @ w_neg.T + b
        z_c_hi = c_hi @ w_pos.T + c_lo @ w_neg.T + b
        z_lo = z_c_lo - (z_a_lo.abs() @ radius.unsqueeze(-1)).squeeze(-1)
        z_hi = z_c_hi + (z_a_hi.abs() @ radius.unsqueeze(-1)).squeeze(-1)
        depth += w.shape[0] + w.shape[1] + 8
        k = depth + d + 8
        total = magnitude @ w.abs().T + b.abs()
        error = (k * UNIT_ROUNDOFF / (1 - k * UNIT_ROUNDOFF)) * 4 * total
        slope, low, high = _relax_layer(layer, z_lo - error, z_hi + error)
        lines.append((slope, low, high))
        magnitude = _magnitudes(layer, lines[-1], magnitude)
        magnitudes.append(magnitude)
        rising = (slope >= 0).unsqueeze(-1)
        s = slope.unsqueeze(-1)
        a_lo, a_hi = torch.where(rising, s * z_a_lo, s * z_a_hi), torch.where(rising, s * z_a_hi, s * z_a_lo)
        c_lo = torch.where(slope >= 0, slope * z_c_lo, slope * z_c_hi) + low
        c_hi = torch.where(slope >= 0, slope * z_c_hi, slope * z_c_lo) + high
    return lines, magnitudes


#: how each layer's pre-activation intervals are found: carried back through the layers below
#: (tightest, ``O(width^3)`` a layer) or forward from the input (``O(width^2 d)``, looser on wide boxes)
INTERMEDIATE = ("backward", "forward")


@on_network_device
def linear_bounds(network: ValueNetwork, x_lo, x_hi, t_lo, t_hi, intermediate: str = "backward") -> Interval:
    """Sound bounds of ``network.raw(x, t)`` over each box (``(B, n)`` corners, times scalars or
    ``(B,)``), by linear relaxations carried back through the layers; intersected with
    :func:`safety.formal.bounds.interval_bounds`. The output is always bounded by back-substitution; the
    pre-activation intervals of the layers below, which the relaxations need, are back-substituted
    too (``intermediate="backward"``, ``O(layers^2 width^3)`` per box) or carried forward
    (``"forward"``, ``O(layers width^2 d)`` for ``d`` inputs, :func:`_forward_pre_activations`)."""
    if intermediate not in INTERMEDIATE:
        raise ValueError(f"intermediate must be one of {INTERMEDIATE}, got {intermediate!r}")
    x_lo, x_hi, t_lo, t_hi = check_box(network, x_lo, x_hi, t_lo, t_hi)
    inputs = (torch.cat([t_lo.unsqueeze(-1), x_lo], -1), torch.cat([t_hi.unsqueeze(-1), x_hi], -1))
    layers, output = _layers(network)
    batch = x_lo.shape[0]
    magnitude = torch.maximum(inputs[0].abs(), inputs[1].abs())
    if intermediate == "forward":
        lines, magnitudes = _forward_pre_activations(layers, inputs, magnitude)
        magnitude = magnitudes[-1]
    else:
        lines = []
        for j, layer in enumerate(layers):
            spec = layer.weight.expand(batch, -1, -1)
            pre = _back_substitute(spec, layer.bias, layers[:j], lines, inputs, magnitude)
            lines.append(_relax_layer(layer, *pre))
            magnitude = _magnitudes(layer, lines[-1], magnitude)
    spec = output.weight.detach().to(torch.float64).expand(batch, -1, -1)
    bias = output.bias.detach().to(torch.float64)
    lo, hi = _back_substitute(spec, bias, layers, lines, inputs, magnitude)
    ibp = interval_bounds(network, x_lo, x_hi, t_lo, t_hi)
    return torch.maximum(lo.squeeze(-1), ibp[0]), torch.minimum(hi.squeeze(-1), ibp[1])
