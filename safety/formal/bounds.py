"""Sound bounds of a value network's output over boxes of states and times: the first block of formal certification.

A formal certificate (issue 43) must prove facts such as ``V(x, T) >= c`` for *every* state of a
box, not for samples. This module bounds the network's raw output ``o(x, t)`` (before the output
map, :meth:`training.network.ValueNetwork.raw`) over many boxes at once, batched with torch:

* :func:`interval_bounds`: interval bound propagation (IBP). Each layer maps an interval to one
  that contains every value: a linear layer by its centre and radius, a sine by where its extrema
  fall, ReLU and tanh by monotonicity, the sin/cos encoding of a heading like a sine. Loose on
  large boxes (the intervals forget how the inputs are correlated) and exact as a box shrinks to a
  point, with an error that shrinks linearly.
* :func:`mean_value_bounds`: the mean-value form ``o(x) in o(c) + [J] (x - c)``, with ``[J]`` an
  interval that contains the input gradient over the whole box (propagated backwards through the
  layers with interval derivatives). As a box shrinks its width tends to the network's own range,
  where IBP's stays a constant factor above it; it is intersected with IBP's, so never looser.

**How tight**: ``python benchmarks/bound_tightness.py`` compares each bound's width with the
linearised range ``2 sum |do/dz_i| r_i`` at a box's centre (measured: docs/results/certificates.md).
IBP stays a constant factor above that range as a box shrinks, the mean-value form tends to it; on
trained networks, whose weights are larger, neither is tight enough to certify a sine network by
branch and bound at a useful box count, and :mod:`safety.formal.linear_bounds` (linear relaxations
carried back through the layers) is.

Both compute in float64 and widen each step outward by an a-priori bound of its own rounding
error (a dot product of ``n`` terms errs by at most ``(n + 2) u sum |w_i h_i|``, ``u = 2**-53``;
``sin``, ``cos`` and ``tanh`` by a few ulps), so the bounds hold for the real-valued network with
the stored weights. A network evaluated in float32 differs from that function by its own rounding
(about 1e-6 relative); a certificate built on these bounds must leave that margin.

Why written here rather than taken from a library: auto_LiRPA's release pins torch < 1.13, and
``bound-propagation`` (which bounds sine) is GPL-3.0, which this MIT package cannot depend on.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from safety.formal.intervals import FUNCTION_ULPS, UNIT_ROUNDOFF, cos_interval, sin_interval
from training.layers import Sine
from training.network import ValueNetwork

Interval = tuple[torch.Tensor, torch.Tensor]


def _widen(lo: torch.Tensor, hi: torch.Tensor, error: torch.Tensor | float) -> Interval:
    return lo - error, hi + error


def _function_error(value_bound: torch.Tensor | float) -> torch.Tensor | float:
    """The rounding error of an elementary function whose result and argument are bounded by ``value_bound``."""
    return FUNCTION_ULPS * UNIT_ROUNDOFF * (1.0 + value_bound)


def linear_interval(layer: nn.Linear, lo: torch.Tensor, hi: torch.Tensor, scale: float = 1.0) -> Interval:
    """Bounds of ``scale * layer(h)`` for ``h`` in ``[lo, hi]``: centre and radius through the weights."""
    w = layer.weight.detach().to(torch.float64) * scale
    b = layer.bias.detach().to(torch.float64) * scale
    centre, radius = 0.5 * (lo + hi), 0.5 * (hi - lo)
    mid = centre @ w.T + b
    spread = radius @ w.abs().T
    magnitude = torch.maximum(lo.abs(), hi.abs()) @ w.abs().T + b.abs()
    error = (w.shape[1] + 4) * UNIT_ROUNDOFF * (magnitude + spread)
    return _widen(mid - spread, mid + spread, error)


def _activation_interval(act: nn.Module, lo: torch.Tensor, hi: torch.Tensor) -> Interval:
    if isinstance(act, nn.ReLU):
        return lo.clamp(min=0.0), hi.clamp(min=0.0)
    if isinstance(act, nn.Tanh):
        error = _function_error(1.0)
        return (torch.tanh(lo) - error).clamp(min=-1.0), (torch.tanh(hi) + error).clamp(max=1.0)
    raise TypeError(f"no interval rule for activation {type(act).__name__}")


def _encoding_interval(network: ValueNetwork, x_lo: torch.Tensor, x_hi: torch.Tensor, t_lo, t_hi) -> Interval:
    """The encoded input's bounds (time, the plain state dimensions, then sin and cos of the headings),
    in the order :meth:`ValueNetwork.encode` builds it."""
    enc = network.encoding
    offset = torch.tensor(enc.state_offset, dtype=torch.float64)
    scale = torch.tensor(enc.state_scale, dtype=torch.float64)
    t_parts = ((t_lo - enc.time_offset) / enc.time_scale, (t_hi - enc.time_offset) / enc.time_scale)
    xs = ((x_lo - offset) / scale, (x_hi - offset) / scale)
    error = 4 * UNIT_ROUNDOFF * (1.0 + torch.maximum(xs[0].abs(), xs[1].abs()))
    xs = _widen(*xs, error)
    t_error = 4 * UNIT_ROUNDOFF * (1.0 + torch.maximum(t_parts[0].abs(), t_parts[1].abs()))
    lows, highs = [(t_parts[0] - t_error).unsqueeze(-1)], [(t_parts[1] + t_error).unsqueeze(-1)]
    if not enc.sincos_dims:
        return torch.cat([*lows, xs[0]], -1), torch.cat([*highs, xs[1]], -1)
    kept = [i for i in range(x_lo.shape[-1]) if i not in enc.sincos_dims]
    angles = list(enc.sincos_dims)
    r = enc.sincos_radius
    s, c = sin_interval(x_lo[..., angles], x_hi[..., angles]), cos_interval(x_lo[..., angles], x_hi[..., angles])
    lows += [xs[0][..., kept], r * s[0], r * c[0]]
    highs += [xs[1][..., kept], r * s[1], r * c[1]]
    return torch.cat(lows, -1), torch.cat(highs, -1)


def on_network_device(function: Callable[..., Any]) -> Callable[..., Any]:
    """Run a bound function with tensor factories defaulting to the network's device (its first
    argument): the boxes and every constant then live where the weights do, CPU or GPU."""

    @functools.wraps(function)
    def wrapped(network: ValueNetwork, *args: Any, **kwargs: Any) -> Any:
        with torch.device(next(network.parameters()).device):
            return function(network, *args, **kwargs)

    return wrapped


def check_box(network: ValueNetwork, x_lo, x_hi, t_lo, t_hi) -> tuple[torch.Tensor, ...]:
    """Boxes of states and times as float64 tensors on the network's device (times expanded to one per
    box), refused naming the problem unless the state corners are two ``(B, n)`` tensors, every corner
    and time is finite, and no lower corner lies above its upper one."""
    n = network.system.state_dim
    device = next(network.parameters()).device
    x_lo, x_hi = (torch.as_tensor(v, dtype=torch.float64).to(device) for v in (x_lo, x_hi))
    t_lo, t_hi = (torch.as_tensor(v, dtype=torch.float64).to(device) for v in (t_lo, t_hi))
    if x_lo.ndim != 2 or x_lo.shape != x_hi.shape or x_lo.shape[-1] != n:
        raise ValueError(
            f"state boxes must be two (B, {n}) tensors of corners, got {tuple(x_lo.shape)} and {tuple(x_hi.shape)}"
        )
    t_lo, t_hi = t_lo.expand(x_lo.shape[0]), t_hi.expand(x_lo.shape[0])
    for name, values in (("state corner", torch.cat([x_lo, x_hi])), ("time", torch.cat([t_lo, t_hi]))):
        if not bool(torch.isfinite(values).all()):
            raise ValueError(f"a box's {name} is not finite (NaN or inf)")
    if bool((x_lo > x_hi).any()) or bool((t_lo > t_hi).any()):
        raise ValueError("a box has a lower corner above its upper corner")
    return x_lo, x_hi, t_lo, t_hi


@on_network_device
def interval_bounds(network: ValueNetwork, x_lo, x_hi, t_lo, t_hi) -> Interval:
    """Sound bounds of ``network.raw(x, t)`` for every ``x`` in each box ``[x_lo, x_hi]`` (``(B, n)``)
    and ``t`` in ``[t_lo, t_hi]`` (scalars or ``(B,)``), by interval bound propagation (float64, CPU)."""
    x_lo, x_hi, t_lo, t_hi = check_box(network, x_lo, x_hi, t_lo, t_hi)
    lo, hi = _propagate(network, *_encoding_interval(network, x_lo, x_hi, t_lo, t_hi))[0]
    return lo.squeeze(-1), hi.squeeze(-1)


def _propagate(network: ValueNetwork, lo: torch.Tensor, hi: torch.Tensor) -> tuple[Interval, list[Interval]]:
    """IBP from encoded-input bounds; also each activated layer's pre-activation bounds (``w0 z`` for
    sines), which the gradient bounds need."""
    pre = []
    for layer, act in zip(network.layers, network.activations):
        if isinstance(act, Sine):
            z = linear_interval(layer, lo, hi, act.w0)
            lo, hi = sin_interval(*z)
        else:
            z = linear_interval(layer, lo, hi)
            lo, hi = _activation_interval(act, *z)
        pre.append(z)
    return linear_interval(network.output, lo, hi), pre


def _derivative_interval(act: nn.Module, lo: torch.Tensor, hi: torch.Tensor) -> Interval:
    """Bounds of the activation's derivative (with respect to the layer's own output ``z``) over its
    pre-activation bounds (``w0 z`` for a sine, whose derivative is ``w0 cos(w0 z)``)."""
    if isinstance(act, Sine):
        c = cos_interval(lo, hi)
        return act.w0 * c[0], act.w0 * c[1]
    if isinstance(act, nn.ReLU):
        return (lo > 0).to(lo.dtype), (hi > 0).to(hi.dtype)  # 0 or 1; both where the box straddles 0
    if isinstance(act, nn.Tanh):
        t_lo, t_hi = torch.tanh(lo), torch.tanh(hi)
        min_abs = torch.where((lo <= 0) & (hi >= 0), torch.zeros_like(lo), torch.minimum(t_lo.abs(), t_hi.abs()))
        max_abs = torch.maximum(t_lo.abs(), t_hi.abs())
        error = _function_error(1.0) * 4  # tanh's rounding, then the square's
        return 1 - (max_abs + error).clamp(max=1.0) ** 2 - error, 1 - (min_abs - error).clamp(min=0.0) ** 2 + error
    raise TypeError(f"no derivative rule for activation {type(act).__name__}")


def _interval_product(a: Interval, b: Interval) -> Interval:
    """Elementwise product of two intervals (the extremes of the four corner products)."""
    corners = torch.stack([a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]])
    error = 4 * UNIT_ROUNDOFF * corners.abs().amax(0)
    return corners.amin(0) - error, corners.amax(0) + error


def _matvec_interval(weight: torch.Tensor, g: Interval) -> Interval:
    """Bounds of ``g @ weight`` for ``g`` in an interval (``weight`` exact, float64)."""
    centre, radius = 0.5 * (g[0] + g[1]), 0.5 * (g[1] - g[0])
    mid, spread = centre @ weight, radius @ weight.abs()
    error = (weight.shape[0] + 4) * UNIT_ROUNDOFF * (torch.maximum(g[0].abs(), g[1].abs()) @ weight.abs() + spread)
    return mid - spread - error, mid + spread + error


@on_network_device
def gradient_bounds(network: ValueNetwork, x_lo, x_hi, t_lo, t_hi) -> Interval:
    """Sound bounds of ``d network.raw / d(encoded input)`` over each box (backward through the layers
    with interval derivatives), shape ``(B, input_dim)``."""
    x_lo, x_hi, t_lo, t_hi = check_box(network, x_lo, x_hi, t_lo, t_hi)
    return _encoded_gradient(network, *_encoding_interval(network, x_lo, x_hi, t_lo, t_hi))


def _encoded_gradient(network: ValueNetwork, lo: torch.Tensor, hi: torch.Tensor) -> Interval:
    _, pre = _propagate(network, lo, hi)
    w_out = network.output.weight.detach().to(torch.float64)  # (1, width)
    g = (w_out.expand(lo.shape[0], -1), w_out.expand(lo.shape[0], -1))
    for layer, act, z in zip(reversed(network.layers), reversed(network.activations), reversed(pre)):
        g = _interval_product(g, _derivative_interval(act, *z))
        w = layer.weight.detach().to(torch.float64)
        g = _matvec_interval(w, g)  # (B, in) = g (B, out) @ W (out, in)
    return g


@on_network_device
def input_gradient_bounds(network: ValueNetwork, x_lo, x_hi, t_lo, t_hi) -> tuple[Interval, Interval]:
    """Sound bounds of ``d network.raw / dt`` (``(B,)``) and ``d network.raw / dx`` (``(B, n)``) over each box."""
    x_lo, x_hi, t_lo, t_hi = check_box(network, x_lo, x_hi, t_lo, t_hi)
    g = _encoded_gradient(network, *_encoding_interval(network, x_lo, x_hi, t_lo, t_hi))
    return _input_jacobian(network, g, x_lo, x_hi)


@on_network_device
def mean_value_bounds(network: ValueNetwork, x_lo, x_hi, t_lo, t_hi) -> Interval:
    """Sound bounds of ``network.raw(x, t)`` over each box by the mean-value form around its centre,
    intersected with :func:`interval_bounds`. The gradient is taken with respect to ``(t, x)`` through
    the encoding (the headings' sin/cos by their interval derivatives)."""
    x_lo, x_hi, t_lo, t_hi = check_box(network, x_lo, x_hi, t_lo, t_hi)
    enc_lo, enc_hi = _encoding_interval(network, x_lo, x_hi, t_lo, t_hi)
    ibp, _ = _propagate(network, enc_lo, enc_hi)
    g = _encoded_gradient(network, enc_lo, enc_hi)
    dt, dx = _input_jacobian(network, g, x_lo, x_hi)
    x_c, t_c = 0.5 * (x_lo + x_hi), 0.5 * (t_lo + t_hi)
    point = _propagate(network, *_encoding_interval(network, x_c, x_c, t_c, t_c))[0]  # o(centre), bounded
    radius = torch.cat([(0.5 * (t_hi - t_lo)).unsqueeze(-1), 0.5 * (x_hi - x_lo)], -1)
    slope = torch.cat([torch.maximum(dt[0].abs(), dt[1].abs()).unsqueeze(-1),
                       torch.maximum(dx[0].abs(), dx[1].abs())], -1)  # fmt: skip
    spread = (slope * radius).sum(-1)
    spread = spread * (1 + 4 * UNIT_ROUNDOFF * slope.shape[-1])
    lo = torch.maximum(point[0].squeeze(-1) - spread, ibp[0].squeeze(-1))
    hi = torch.minimum(point[1].squeeze(-1) + spread, ibp[1].squeeze(-1))
    return lo, hi


def _input_jacobian(network: ValueNetwork, g: Interval, x_lo, x_hi) -> tuple[Interval, Interval]:
    """From the encoded-input gradient bounds to bounds of ``d o / dt`` and ``d o / dx``."""
    enc = network.encoding
    n = x_lo.shape[-1]
    scale = torch.tensor(enc.state_scale, dtype=torch.float64)
    dt = (g[0][:, 0] / enc.time_scale, g[1][:, 0] / enc.time_scale)
    body = (g[0][:, 1:], g[1][:, 1:])
    if not enc.sincos_dims:
        return dt, (body[0] / scale, body[1] / scale)
    kept = [i for i in range(n) if i not in enc.sincos_dims]
    angles = list(enc.sincos_dims)
    k, m = len(kept), len(angles)
    r = enc.sincos_radius
    dx_lo, dx_hi = torch.empty_like(x_lo), torch.empty_like(x_lo)
    dx_lo[:, kept], dx_hi[:, kept] = body[0][:, :k] / scale[kept], body[1][:, :k] / scale[kept]
    s = sin_interval(x_lo[:, angles], x_hi[:, angles])
    c = cos_interval(x_lo[:, angles], x_hi[:, angles])
    # d/dtheta [r sin, r cos] = r (cos, -sin): do/dtheta = r (g_sin cos - g_cos sin)
    g_sin = (body[0][:, k : k + m], body[1][:, k : k + m])
    g_cos = (body[0][:, k + m :], body[1][:, k + m :])
    a = _interval_product(g_sin, c)
    b = _interval_product(g_cos, s)
    dx_lo[:, angles], dx_hi[:, angles] = r * (a[0] - b[1]), r * (a[1] - b[0])
    widen = 4 * UNIT_ROUNDOFF * (dx_hi.abs() + dx_lo.abs())
    return dt, (dx_lo - widen, dx_hi + widen)
