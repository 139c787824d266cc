"""Value networks of any activation layout, with input encoding and output parameterisation.

A layout is a string with one letter per activated hidden layer and a final ``l`` (linear output):
``s`` sine ``sin(w0 z)``, ``r`` ReLU, ``t`` tanh. ``"ssrsl"`` is sine, sine, ReLU, sine, linear. The
layers, their activations and their initialisation live in :mod:`training.layers`.

Inputs ``(t, x)`` are encoded by an :class:`~training.encoding.Encoding` (affine maps to about [-1, 1]; optionally
``(sin, cos)`` of periodic dimensions). Outputs: ``vanilla`` ``V = value_scale o + value_offset``
(DeepReach) or ``exact`` ``V = b(x) + (t / T) value_scale o``, which meets the boundary condition
``V(x, 0) = b(x)`` by construction (``b`` is the system's
:meth:`~reach.systems.base.ControlAffineSystem.boundary_value`: ``l``, or ``max(l, -g)`` for a
reach-avoid problem). A reach-avoid network may also hold its constraint ``V >= -g`` at every time
by construction, ``exact-constraint``: ``V = max(b(x) + (t / T) value_scale o, -g(x))`` (see
docs/training.md for what each is, docs/results/training.md for what each costs and wins).
"""

from __future__ import annotations

from typing import Any, Literal, NamedTuple

import torch
from torch import nn

from reach.systems import ControlAffineSystem
from reach.validation import positive_finite
from reach.value_function import check_time
from training.encoding import Encoding
from training.layers import activate_in_place, init_linear, make_activation, parse_layout

Parameterisation = Literal["exact", "vanilla", "exact-constraint", "diff"]
#: the output parameterisations (:class:`ValueNetwork`); ``exact-constraint`` is for reach-avoid systems;
#: ``diff`` is DeepReach's ``diff_model`` (``V = b(x) + scale * o``), kept for its checkpoints
PARAMETERISATIONS = ("exact", "vanilla", "exact-constraint", "diff")
#: the parameterisations whose ``V(x, 0)`` is learned, not built in: they train with boundary points
#: and a boundary loss (and may pretrain on it)
LEARNED_BOUNDARY = ("vanilla", "diff")


class Margins(NamedTuple):
    """What the exact parameterisations and the residual read of the system at a batch of states,
    computed once per step outside any compiled region (none depends on the network's weights).

    ``boundary`` is ``V(x, 0)`` and ``boundary_gradient`` its ``d/dx``; ``terminal`` the ``l`` of the
    variational inequality; ``constraint`` and ``constraint_gradient`` reach-avoid's ``g`` and
    ``dg/dx`` (None for other kinds)."""

    boundary: torch.Tensor
    boundary_gradient: torch.Tensor
    terminal: torch.Tensor
    constraint: torch.Tensor | None = None
    constraint_gradient: torch.Tensor | None = None


def check_parameterisation(parameterisation: object, system: ControlAffineSystem) -> str:
    """``parameterisation`` if it is one of :data:`PARAMETERISATIONS` and suits ``system``'s kind."""
    if parameterisation not in PARAMETERISATIONS:
        raise ValueError(f"parameterisation must be one of {PARAMETERISATIONS}, got {parameterisation!r}")
    if parameterisation == "exact-constraint" and not system.problem.has_constraint:
        raise ValueError(
            f"parameterisation 'exact-constraint' holds a reach-avoid constraint; {system.name} is a "
            f"{system.kind} problem (use 'exact')"
        )
    return str(parameterisation)


class ValueNetwork(nn.Module):
    """``V(x, t)`` as an MLP of the given layout (see the module docstring).

    Args:
        system: the system whose value this is (gives ``l(x)``, dimensions and default encoding).
        layout: e.g. ``"ssssl"`` (DeepReach's 4 sine layers + linear output) or ``"ssrsl"``.
        width: neurons per hidden layer.
        parameterisation: ``"exact"``, ``"vanilla"``, (reach-avoid) ``"exact-constraint"`` or
            ``"diff"`` (DeepReach's ``diff_model``: ``V = b(x) + value_scale * o``, no time factor).
        w0: sine frequency.
        encoding: input/output encoding (default: :meth:`Encoding.for_system`).
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        layout: str = "ssssl",
        width: int = 128,
        parameterisation: Parameterisation = "exact",
        w0: float = 30.0,
        encoding: Encoding | None = None,
    ) -> None:
        super().__init__()
        letters = parse_layout(layout)
        if isinstance(width, bool) or not isinstance(width, int) or width < 1:
            raise ValueError(f"width must be a positive integer, got {width!r}")
        check_parameterisation(parameterisation, system)
        w0 = positive_finite("w0", w0)
        self.system = system
        self.layout = layout
        self.width = width
        self.parameterisation = parameterisation
        self.w0 = float(w0)
        self.encoding = encoding if encoding is not None else Encoding.for_system(system)
        if len(self.encoding.state_scale) != system.state_dim:
            raise ValueError(
                f"encoding has {len(self.encoding.state_scale)} state scales, {system.name} has {system.state_dim}"
            )
        in_dim = self.encoding.input_dim(system.state_dim)
        self.layers = nn.ModuleList()
        self.activations = nn.ModuleList()
        previous = None
        for letter in letters:
            layer = nn.Linear(in_dim, width)
            init_linear(layer, letter, previous, self.w0)
            self.layers.append(layer)
            self.activations.append(make_activation(letter, self.w0))
            in_dim, previous = width, letter
        self.output = nn.Linear(in_dim, 1)
        init_linear(self.output, "l", previous, self.w0)
        enc = self.encoding
        self.register_buffer("_offset", torch.tensor(enc.state_offset, dtype=torch.float32), persistent=False)
        self.register_buffer("_scale", torch.tensor(enc.state_scale, dtype=torch.float32), persistent=False)
        # the sin/cos-encoded dimensions and the others as index tensors on the network's device: a list
        # index would copy from the CPU at every call, which a CUDA graph cannot capture
        sincos = list(enc.sincos_dims or ())
        kept = [i for i in range(system.state_dim) if i not in sincos]
        self.register_buffer("_angle_index", torch.tensor(sincos, dtype=torch.long), persistent=False)
        self.register_buffer("_kept_index", torch.tensor(kept, dtype=torch.long), persistent=False)
        order = torch.tensor(kept + sincos, dtype=torch.long)  # state dims as the encoding lists them
        self.register_buffer("_state_order", torch.argsort(order), persistent=False)

    # ------------------------------------------------------------------ description
    def architecture(self) -> dict[str, Any]:
        """Everything needed to rebuild this network (stored in checkpoints)."""
        return {
            "system": self.system.config(),
            "layout": self.layout,
            "width": self.width,
            "parameterisation": self.parameterisation,
            "w0": self.w0,
            "encoding": self.encoding.to_dict(),
        }

    # ------------------------------------------------------------------ forward
    def encode(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        enc = self.encoding
        xs = (x - self._offset.to(x.dtype)) / self._scale.to(x.dtype)
        parts = [((t - enc.time_offset) / enc.time_scale).unsqueeze(-1), xs]
        if enc.sincos_dims:
            angles = x.index_select(-1, self._angle_index)
            r = enc.sincos_radius
            parts = [parts[0], xs.index_select(-1, self._kept_index), r * torch.sin(angles), r * torch.cos(angles)]
        return torch.cat(parts, dim=-1)

    def raw(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The network output ``o`` before the output parameterisation.

        Without autograd (every value a rollout, a filter or a sampler reads) each activation is
        applied in the layer's own output, bit for bit the same values, and faster where these layers
        are memory-bound, as on CPUs (measured: docs/results/verification.md, *Rollout engine*)."""
        h = self.encode(x, t)
        in_place = not torch.is_grad_enabled()
        for layer, act in zip(self.layers, self.activations):
            z = layer(h)
            h = activate_in_place(act, z) if in_place else act(z)
        return self.output(h).squeeze(-1)

    def _raw_and_input_gradient(
        self, h: torch.Tensor, matmul_dtype: torch.dtype | None = None, inplace: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Output ``o`` and ``do/dh`` for encoded inputs ``h`` in one forward pass plus one product per layer.

        The input gradient of an MLP is ``W_1^T diag(a_1') ... W_L^T diag(a_L') w_out``: the forward
        pass keeps each activation's derivative (``w0 cos(w0 z)`` for sine, 1 where ``z > 0`` for ReLU,
        ``1 - h^2`` for tanh) and one matrix product per layer carries the gradient back. That is the
        arithmetic reverse-mode autograd does for an input gradient, minus its bookkeeping. With
        ``inplace`` (inference only) buffers are reused; without it every operation is an ordinary
        differentiable one, so autograd can take parameter gradients *of* this input gradient with a
        first-order backward pass (no ``create_graph`` double backward), which is what training uses.
        """
        slopes = []
        weights = []
        for index, (layer, letter) in enumerate(zip(self.layers, self.layout[:-1])):
            w, b = layer.weight, layer.bias
            if letter == "s":  # fold w0 into the layer: sin(w0 z) = sin(z'), d/dh = cos(z') (w0 W)
                w, b = self.w0 * w, self.w0 * b
            if matmul_dtype is not None and index > 0:
                w = w.to(matmul_dtype)
                z = (h.to(matmul_dtype) @ w.T).to(h.dtype) + b  # the bias stays in full precision
            else:
                z = torch.nn.functional.linear(h, w, b)
            weights.append(w)
            if letter == "s":
                h = torch.sin(z)
                slopes.append(z.cos_() if inplace else torch.cos(z))
            elif letter == "r":
                h = torch.relu(z)
                # 1 where z > 0, else 0, computed in float from h: a bool mask (z > 0) made torch.compile's
                # CPU kernels store and reload byte masks, which cost more than the layer's matmul
                # (measured: docs/results/training.md, *Training throughput*)
                slopes.append(torch.sign(h))
            else:
                h = torch.tanh(z)
                slopes.append(1.0 - h * h)
        o = self.output(h).squeeze(-1)
        g = self.output.weight[0].to(h.dtype)
        for w, slope in zip(reversed(weights), reversed(slopes)):
            g = slope.mul_(g) if inplace else slope * g
            g = (g.to(w.dtype) @ w).to(slope.dtype) if w.dtype != slope.dtype else g @ w
        return o, g

    def _state_gradient(self, g: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``do/dx`` from ``do/d(encoded input)`` (time input dropped), through the state encoding."""
        enc = self.encoding
        g = g[..., 1:]  # drop the time input
        state_scale = self._scale.to(x.dtype)
        if not enc.sincos_dims:
            return g / state_scale
        m = len(enc.sincos_dims)
        k = x.shape[-1] - m
        angles = x.index_select(-1, self._angle_index)
        kept = g[..., :k] / state_scale.index_select(0, self._kept_index)
        r = enc.sincos_radius
        d_sin, d_cos = g[..., k : k + m], g[..., k + m :]
        turned = r * (d_sin * torch.cos(angles) - d_cos * torch.sin(angles))
        return torch.cat([kept, turned], dim=-1).index_select(-1, self._state_order)

    @torch.no_grad()
    def value_and_gradient(
        self, x: torch.Tensor, t: torch.Tensor, matmul_dtype: torch.dtype | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``V(x, t)`` and ``dV/dx`` in one pass, without building an autograd graph of the network.

        See :meth:`_raw_and_input_gradient`; the rollout engine calls this once per state and step.
        Only ``l(x)``'s small graph (exact parameterisation) uses autograd. Agrees with
        ``torch.autograd.grad`` of :meth:`forward` (tested).

        ``matmul_dtype`` (e.g. ``torch.bfloat16``) runs the hidden-to-hidden products, forward and
        back, in that precision (inputs and weights rounded, fp32 accumulation on CPUs with bf16
        dot products): faster where the hardware has them, and inexact (measured:
        docs/results/verification.md, *Rollout engine*). The first layer, activations and output stay
        in float32.
        """
        o, g = self._raw_and_input_gradient(self.encode(x, t), matmul_dtype, inplace=True)
        margins = self.margins(x) if self.parameterisation != "vanilla" else None
        offset, d_offset, scale, _ = self.output_map(x, t, margins)
        v, dv_dx = offset + scale * o, d_offset + _per_state(scale) * self._state_gradient(g, x)
        if self.parameterisation == "exact-constraint":
            v, dv_dx, _ = hold_constraint(v, dv_dx, None, margins)
        return v, dv_dx

    def margins(self, x: torch.Tensor) -> Margins:
        """The system's :class:`Margins` at states ``x`` (autograd on the margins alone; none depends
        on the parameters)."""
        system = self.system
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            terminal = system.terminal_margin(xg)
            if not system.problem.has_constraint:
                (dl,) = torch.autograd.grad(terminal.sum(), xg)
                return Margins(terminal.detach(), dl, terminal.detach())
            g = system.constraint_margin(xg)
            boundary = system.problem.boundary_value(terminal, g)
            db, dg = (torch.autograd.grad(f.sum(), xg, retain_graph=True)[0] for f in (boundary, g))
        return Margins(boundary.detach(), db, terminal.detach(), g.detach(), dg)

    def failure_margin_and_gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``V(x, 0)`` and its gradient (the failure margin ``l`` and ``dl/dx`` for an avoid system);
        :meth:`margins` has them all."""
        margins = self.margins(x)
        return margins.boundary, margins.boundary_gradient

    def margin_slope(self, samples: int = 65536, seed: int = 0) -> float:
        """The failure margin's steepest slope in the network's normalised coordinates: the largest
        ``|dl/dx * s|`` (2-norm, ``s`` the state scales) over ``samples`` uniform domain states.

        A yardstick for how steep the value may be: ``V`` starts as ``l`` and, for the games here,
        stays within a few times ``l``'s slope (Air3D: 1 for ``l``, at most 1.7 for ``V`` at t = 1.1
        by the grid ground truth). Training's gradient bound is a multiple of it."""
        generator = torch.Generator().manual_seed(seed)
        p = next(self.parameters())
        x = self.system.sample_states(samples, generator=generator).to(device=p.device, dtype=p.dtype)
        dl = self.margins(x).boundary_gradient
        return float(torch.linalg.vector_norm(dl * self._scale.to(dl.dtype), dim=-1).max())

    def value_and_derivatives(
        self, x: torch.Tensor, t: torch.Tensor, margins: Margins | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(V, dV/dx, dV/dt)``, differentiable with respect to the parameters (for training).

        The input derivatives come from :meth:`_raw_and_input_gradient`, so a training step needs one
        ordinary backward pass instead of autograd's double backward, and the whole step is a plain
        first-order graph that ``torch.compile`` can fuse. ``margins`` (:meth:`margins`, exact
        parameterisations) may be passed in when computed outside a compiled region.
        Agrees with autograd's ``create_graph`` input gradients to float32 round-off (tested).
        """
        o, g = self._raw_and_input_gradient(self.encode(x, t))
        do_dx = self._state_gradient(g, x)
        do_dt = g[..., 0] / self.encoding.time_scale
        if self.parameterisation != "vanilla" and margins is None:
            margins = self.margins(x)
        offset, d_offset, scale, d_scale = self.output_map(x, t, margins)
        v, dv_dx, dv_dt = offset + scale * o, d_offset + _per_state(scale) * do_dx, d_scale * o + scale * do_dt
        if self.parameterisation == "exact-constraint":
            return hold_constraint(v, dv_dx, dv_dt, margins)
        return v, dv_dx, dv_dt

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``V(x, t)`` for states ``(..., n)`` and times ``(...)``."""
        o = self.raw(x, t)
        if self.parameterisation == "vanilla":
            offset, _, scale, _ = self.output_map(x, t)
            return offset + scale * o
        # the margins stay differentiable in x here: autograd's double-backward training path needs them
        system = self.system
        scale = self.encoding.value_scale if self.parameterisation == "diff" else self._exact_scale(t)[0]
        v = system.boundary_value(x) + scale * o
        return torch.maximum(v, -system.constraint_margin(x)) if self.parameterisation == "exact-constraint" else v

    def output_map(self, x: torch.Tensor, t: torch.Tensor, margins: Margins | None = None) -> tuple[Any, Any, Any, Any]:
        """The output parameterisation's affine part, written once: ``V = offset + scale * o`` for the
        raw output ``o`` (``exact-constraint`` then takes ``max(V, -g)``, :func:`hold_constraint`).

        Returns ``(offset, d offset / dx, scale, d scale / dt)``: ``vanilla`` (DeepReach) has
        ``offset = value_offset``, ``scale = value_scale``; the exact ones have ``offset = b(x)``
        (``V(x, 0)``) and ``scale = value_scale * t / horizon``, so ``V(x, 0) = b(x)`` for any weights.
        ``margins`` (:meth:`margins`) may be passed in when computed elsewhere (outside a compiled
        region, or differentiably)."""
        enc = self.encoding
        if self.parameterisation == "vanilla":
            return enc.value_offset, 0.0, enc.value_scale, 0.0
        if margins is None:
            margins = self.margins(x)
        if self.parameterisation == "diff":  # DeepReach's diff_model: the boundary plus a constant scale
            return margins.boundary, margins.boundary_gradient, enc.value_scale, 0.0
        return margins.boundary, margins.boundary_gradient, *self._exact_scale(t)

    def _exact_scale(self, t: torch.Tensor) -> tuple[Any, float]:
        """The exact parameterisations' factor of the raw output, ``value_scale * t / horizon``, and
        its time derivative: zero at ``t = 0``, so ``V(x, 0)`` is the boundary value."""
        rate = self.encoding.value_scale / self.encoding.horizon
        return rate * t, rate


def hold_constraint(
    v: torch.Tensor, dv_dx: torch.Tensor, dv_dt: torch.Tensor | None, margins: Margins
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """``max(V, -g)`` with its derivatives: where the constraint binds, ``V = -g``, ``dV/dx = -dg/dx``
    and ``dV/dt = 0`` (the ``exact-constraint`` parameterisation; ties take the network's branch)."""
    g, dg = margins.constraint, margins.constraint_gradient
    binds = v < -g
    v = torch.where(binds, -g, v)
    dv_dx = torch.where(binds.unsqueeze(-1), -dg.to(dv_dx.dtype), dv_dx)
    return v, dv_dx, None if dv_dt is None else torch.where(binds, 0.0, dv_dt)


def _per_state(scale: Any) -> Any:
    """A per-state factor ``(...)`` broadcast against gradients ``(..., n)`` (scalars as they are)."""
    return scale.unsqueeze(-1) if isinstance(scale, torch.Tensor) and scale.ndim else scale


class NeuralValueFunction:
    """A :class:`ValueNetwork` behind the value-function interface (``value``, ``gradient``)."""

    def __init__(self, network: ValueNetwork, matmul_dtype: torch.dtype | None = None) -> None:
        self.network = network
        self.system = network.system
        #: precision of the hidden products in :meth:`value_and_gradient` (None: the network's own)
        self.matmul_dtype = matmul_dtype

    def with_matmul_dtype(self, dtype: torch.dtype | None) -> NeuralValueFunction:
        """The same network whose fused value-and-gradient pass multiplies in ``dtype``."""
        return NeuralValueFunction(self.network, dtype)

    @property
    def time_range(self) -> tuple[float, float]:
        """The network is trained on times-to-go ``[0, horizon]``; it refuses others (no extrapolation)."""
        return (0.0, float(self.system.horizon))

    def _inputs(self, x: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if not isinstance(x, torch.Tensor) or x.ndim == 0 or x.shape[-1] != self.system.state_dim:
            shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise ValueError(f"states must have shape (..., {self.system.state_dim}), got {shape}")
        check_time(t, *self.time_range)
        p = next(self.network.parameters())
        # checked after the cast: a float64 state of 1e300 is finite, but inf in the network's float32
        xc = x.to(device=p.device, dtype=p.dtype)
        finite = torch.isfinite(xc).all(-1)
        if not bool(finite.all()):
            bad = x[~finite.to(x.device)][0].tolist()
            raise ValueError(f"states contain NaN or inf (or overflow {p.dtype}), e.g. {bad}")
        return self._prepared(xc, t)

    def _prepared(self, x: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """States in the weights' device and dtype, headings wrapped, and times broadcast to the batch."""
        p = next(self.network.parameters())
        # headings are wrapped first: the network was trained on [-pi, pi), and V must not depend
        # on which multiple of 2 pi a caller's heading carries
        xc = self.system.wrap(x.to(device=p.device, dtype=p.dtype))
        tt = torch.broadcast_to(torch.as_tensor(t, dtype=p.dtype, device=p.device), xc.shape[:-1])
        return xc, tt

    def unchecked(self) -> NeuralValueFunction:
        """The same network without the value-dependent checks of states and times (NaN, inf, the
        time range), for a graph trace (:mod:`safety.filters.export`): a trace cannot branch on values, and
        the exported filter's runtime makes these checks before it runs the graph."""
        return _UncheckedNeuralValueFunction(self.network, self.matmul_dtype)

    @torch.no_grad()
    def value(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """``V(x, t)`` on the states' device and dtype, wherever the weights are (as a grid's value
        is): a minimum of a GPU network and a grid adds tensors of one device."""
        xi, tt = self._inputs(x, t)
        return self.network(xi, tt).to(device=x.device, dtype=x.dtype)

    def gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        return self.value_and_gradient(x, t)[1]

    def value_and_gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(V, dV/dx)`` from one forward pass (see :meth:`ValueNetwork.value_and_gradient`)."""
        xi, tt = self._inputs(x, t)
        v, g = self.network.value_and_gradient(xi, tt, self.matmul_dtype)
        return v.to(device=x.device, dtype=x.dtype), g.to(device=x.device, dtype=x.dtype)

    def autograd_gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """``dV/dx`` by ``torch.autograd`` (the reference the fast path is tested against)."""
        xi, tt = self._inputs(x, t)
        with torch.enable_grad():
            xi = xi.detach().requires_grad_(True)
            (g,) = torch.autograd.grad(self.network(xi, tt).sum(), xi)
        return g.to(device=x.device, dtype=x.dtype)


class _UncheckedNeuralValueFunction(NeuralValueFunction):
    """:meth:`NeuralValueFunction.unchecked`: inputs prepared (cast, headings wrapped), not checked."""

    def _inputs(self, x: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self._prepared(x, t)
