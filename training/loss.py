"""The HJI variational-inequality residual and the training loss.

With ``t`` time-to-go, the value of an avoid or reach problem solves ``max(dV/dt - H, V - l(x)) = 0``
(``H`` with the kind's objectives, see docs/concepts.md), and a reach-avoid value
``min(max(dV/dt - H, V - l(x)), V + g(x)) = 0`` (``l`` the target margin, ``g`` the constraint
margin: DeepReach's ``brat_hjivi``, the continuous form of the grid's ``V <- max(min(V, l), -g)``).
The residual is that left-hand side at sampled ``(x, t)``; the loss is its mean absolute value
(``l1``) or mean square (``l2``). The vanilla parameterisation adds a boundary term
``|V(x, 0) - b(x)|`` on the points sampled at ``t = 0`` (``b = l``, or ``max(l, -g)`` for
reach-avoid).

The input derivatives ``dV/dx``, ``dV/dt`` come one of two ways (``gradients``):

* ``"autograd"``: ``torch.autograd.grad(V, (x, t), create_graph=True)``, DeepReach's way; the
  training step then differentiates through autograd's own backward pass (double backward);
* ``"fused"`` (default): :meth:`ValueNetwork.value_and_derivatives` carries the input gradient
  through the layers by hand in the forward pass, so the step is one forward and one ordinary
  backward pass. Same numbers (tested to float32 round-off), fewer and larger operations, and a
  graph that ``torch.compile`` can fuse (:func:`residual_function`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch

from reach.compiling import maybe_compile
from reach.validation import check_float
from training.network import LEARNED_BOUNDARY, Margins, ValueNetwork

GRADIENTS = ("fused", "autograd")
Terms = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
#: ``residual_fn(x, t) -> (residual, V, dV/dx)`` at states ``(N, n)`` and times ``(N,)``, graph kept for training
ResidualFunction = Callable[[torch.Tensor, torch.Tensor], Terms]


def hji_residual(network: ValueNetwork, x: torch.Tensor, t: torch.Tensor, gradients: str = "autograd") -> Terms:
    """``(residual, V, dV/dx)`` at states ``(N, n)`` and times ``(N,)``; keeps the graph for training."""
    if gradients not in GRADIENTS:
        raise ValueError(f"gradients must be one of {GRADIENTS}, got {gradients!r}")
    system = network.system
    if gradients == "autograd":
        x = x.detach().requires_grad_(True)
        t = t.detach().requires_grad_(True)
        v = network(x, t)
        dv_dx, dv_dt = torch.autograd.grad(v.sum(), (x, t), create_graph=True)
        x = x.detach()
        terminal = system.terminal_margin(x)
        constraint = system.constraint_margin(x) if system.problem.has_constraint else None
    else:
        margins = network.margins(x)
        v, dv_dx, dv_dt = network.value_and_derivatives(x, t, margins)
        terminal, constraint = margins.terminal, margins.constraint
    return _residual(network, x.detach(), v, dv_dx, dv_dt, terminal, constraint), v, dv_dx


def _residual(
    network: ValueNetwork,
    x: torch.Tensor,
    v: torch.Tensor,
    dv_dx: torch.Tensor,
    dv_dt: torch.Tensor,
    terminal: torch.Tensor,
    constraint: torch.Tensor | None,
) -> torch.Tensor:
    """The kind's variational inequality: ``max(dV/dt - H, V - l)``, then ``min(., V + g)`` where a
    constraint must hold (the Hamiltonian carries the kind's objectives)."""
    residual = torch.maximum(dv_dt - network.system.hamiltonian(x, dv_dx), v - terminal)
    return residual if constraint is None else torch.minimum(residual, v + constraint)


def residual_function(
    network: ValueNetwork, gradients: str = "fused", compile: bool | None = False
) -> ResidualFunction:
    """``residual_fn(x, t) -> (residual, V)`` for training ``network``.

    ``compile`` (fused gradients only): ``True`` compiles the residual with ``torch.compile``,
    ``None`` tries to and falls back to eager mode with a warning (no C++ compiler, ...), ``False``
    stays eager. Compiling fuses each layer's ``sin``, ``cos`` and products (and their backward)
    into a few kernels, so the default network's step runs faster than eager fused and than
    autograd's double backward; the first step pays the compilation (measured:
    docs/results/training.md, *Training throughput*).
    """
    if gradients not in GRADIENTS:
        raise ValueError(f"gradients must be one of {GRADIENTS}, got {gradients!r}")
    if gradients == "autograd":
        if compile:
            raise ValueError("compile needs gradients='fused' (torch.compile does not take double backward)")
        return lambda x, t: hji_residual(network, x, t, "autograd")

    def fused(
        x: torch.Tensor,
        t: torch.Tensor,
        boundary: torch.Tensor,
        d_boundary: torch.Tensor,
        terminal: torch.Tensor,
        constraint: torch.Tensor | None,
        d_constraint: torch.Tensor | None,
    ) -> Terms:
        margins = Margins(boundary, d_boundary, terminal, constraint, d_constraint)
        v, dv_dx, dv_dt = network.value_and_derivatives(x, t, margins)
        return _residual(network, x, v, dv_dx, dv_dt, terminal, constraint), v, dv_dx

    body = maybe_compile(fused, compile, "training", own_cache=True)  # guards on this network fail for the next one

    def residual_fn(x: torch.Tensor, t: torch.Tensor) -> Terms:
        return body(x, t, *network.margins(x))  # autograd on the margins alone, outside the compiled graph

    return residual_fn


@dataclass(frozen=True)
class LossWeights:
    """How the loss's terms are measured and weighed against the residual: the norm of the residual
    and of the vanilla boundary gap (``"l1"`` or ``"l2"``) and each optional term's weight. A run's
    :class:`~training.config.TrainConfig` holds these (``loss`` and the ``*_weight`` fields), and the
    trainer's objective passes them whole."""

    norm: str = "l1"
    boundary: float = 1.0
    gradient: float = 1.0
    upper_bound: float = 1.0
    lower_bound: float = 1.0

    def __post_init__(self) -> None:
        if self.norm not in ("l1", "l2"):
            raise ValueError(f"loss norm must be 'l1' or 'l2', got {self.norm!r}")
        for name in ("boundary", "gradient", "upper_bound", "lower_bound"):
            check_float(f"{name} weight", getattr(self, name), 0)


class RefutedPoints(NamedTuple):
    """One step's points ``(x (M, n), t (M,))`` from which the network's own policy was seen to fail
    (:mod:`studies.train_until`), and how the refuted-claims term weighs them: ``sign`` turns ``V``
    so that ``> 0`` is its claim (``+1`` avoid, ``-1`` reach kinds), ``margin`` how far past the zero
    level the claim is pushed, ``weight`` the term's weight."""

    x: torch.Tensor
    t: torch.Tensor
    sign: float
    margin: float
    weight: float


class Anchors(NamedTuple):
    """What a step knows of the value beside its residual, each term optional (:func:`loss_terms`
    says how each counts): ``upper_bound`` per point (``+inf`` where unknown), ``lower_bound``
    labelled points ``(x, t, J)``, ``refuted`` the refuted-claims term's points."""

    upper_bound: torch.Tensor | None = None
    lower_bound: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    refuted: RefutedPoints | None = None


@dataclass(frozen=True)
class LossSettings:
    """What a run's loss is fixed to before its first step, passed whole to :func:`loss_terms`.

    Attributes:
        residual_fn: computes the HJI residual (from :func:`residual_function`); ``None``: autograd's.
        gradient_bound: the gradient term's bound on ``|dV/dx * s|`` in the network's normalised
            coordinates; ``None``: no gradient term.
        weights: the norm and each optional term's weight (:class:`LossWeights`).
    """

    residual_fn: ResidualFunction | None = None
    gradient_bound: float | None = None
    weights: LossWeights = field(default_factory=LossWeights)

    def __post_init__(self) -> None:
        if self.residual_fn is not None and not callable(self.residual_fn):
            raise ValueError(f"residual_fn must be callable (see residual_function), got {self.residual_fn!r}")
        if self.gradient_bound is not None:
            check_float("gradient_bound", self.gradient_bound, 0)
        if not isinstance(self.weights, LossWeights):
            raise ValueError(f"weights must be a LossWeights, got {self.weights!r}")


def training_loss(
    network: ValueNetwork,
    x: torch.Tensor,
    t: torch.Tensor,
    **options: Any,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Scalar loss and its terms as floats for logging: :func:`loss_terms` with each term read back
    (one device synchronisation for all of them)."""
    total, terms = loss_terms(network, x, t, **options)
    return total, terms_to_floats(terms)


def terms_to_floats(terms: dict[str, torch.Tensor]) -> dict[str, float]:
    """The loss terms read back as floats, all in one transfer (each ``float(tensor)`` on a GPU waits
    for the device on its own)."""
    values = torch.stack([v.detach().reshape(()).to(torch.float32) for v in terms.values()]).tolist()
    return dict(zip(terms, values))


def loss_terms(
    network: ValueNetwork,
    x: torch.Tensor,
    t: torch.Tensor,
    *,
    pde: bool = True,
    boundary_mask: torch.Tensor | None = None,
    anchors: Anchors | None = None,
    settings: LossSettings | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Scalar loss and its terms (``pde``, ``boundary``, ``gradient``, ...) as detached 0-d tensors:
    nothing here reads a value back from the device (except the vanilla boundary mask's ``any``), so
    a CUDA graph can capture it (:mod:`training.cuda_graph`).

    ``settings`` (:class:`LossSettings`, default ``LossSettings()``) holds what is fixed for a run:
    the residual function (default: autograd's), the gradient bound and the :class:`LossWeights`
    (the norm and each optional term's weight).

    ``settings.gradient_bound`` adds ``weights.gradient * mean(relu(|dV/dx * s| - bound))``, ``s`` the
    encoding's state scales (the gradient in the network's normalised coordinates, 2-norm). Value
    functions are Lipschitz, but the residual alone admits networks with a cliff: a thin wall where
    ``V`` drops by a finite amount and continues on a wrong branch. The wall violates the PDE only on a
    sliver of the domain, which the mean residual barely sees; the bound removes it (see the README's
    training section for the Air3D case that motivated it).

    ``anchors`` (:class:`Anchors`) holds the optional terms below. ``upper_bound`` (per point,
    ``+inf`` where unknown) adds ``upper_bound_weight * mean(relu(V - upper_bound))`` over all
    points: a known upper bound of the true value (the union of pairwise BRTs for a multi-vehicle
    system), which the residual alone does not enforce.

    ``lower_bound`` = ``(x, t, J)``: labelled points with a known lower bound ``J`` of the true value
    (:func:`training.policy_lower_bounds.policy_lower_bound`) add ``weights.lower_bound * mean(relu(J - V(x, t)))``.

    ``refuted`` (:class:`RefutedPoints`): points from which the network's own policy failed add
    ``weight * mean(relu(sign * V(x, t) + margin))``. Not a bound of the true value (another policy may
    succeed from there) but of what this network may claim: a safety filter acts on the claim with
    this very policy, so a claim its rollout refutes is the error that matters. It pushes ``V`` to the
    conservative side, where the residual alone may not: a network can meet the residual with a
    value that claims too much (docs/results/training.md, the quadrotor).
    """
    if settings is None:
        settings = LossSettings()
    residual_fn, gradient_bound, weights = settings.residual_fn, settings.gradient_bound, settings.weights
    upper_bound, lower_bound, refuted = anchors if anchors is not None else Anchors()
    terms: dict[str, torch.Tensor] = {}
    total = x.new_zeros(())
    if pde:
        residual, v, dv_dx = (residual_fn or (lambda a, b: hji_residual(network, a, b)))(x, t)
        pde_loss = residual.abs().mean() if weights.norm == "l1" else residual.square().mean()
        total = total + pde_loss
        terms["pde"] = pde_loss.detach()
        if gradient_bound is not None:
            scale = network._scale.to(dv_dx.dtype)
            excess = torch.relu(torch.linalg.vector_norm(dv_dx * scale, dim=-1) - gradient_bound).mean()
            total = total + weights.gradient * excess
            terms["gradient"] = excess.detach()
    else:
        v = network(x, t)
    if upper_bound is not None:
        known = torch.isfinite(upper_bound)
        excess = torch.where(known, torch.relu(v - torch.where(known, upper_bound, v.detach())), 0.0).mean()
        total = total + weights.upper_bound * excess
        terms["upper_bound"] = excess.detach()
    if lower_bound is not None:
        x_label, t_label, floor = lower_bound
        shortfall = torch.relu(floor - network(x_label, t_label)).mean()
        total = total + weights.lower_bound * shortfall
        terms["lower_bound"] = shortfall.detach()
    if refuted is not None:
        claim = refuted.sign * network(refuted.x, refuted.t)
        excess = torch.relu(claim + refuted.margin).mean()
        total = total + refuted.weight * excess
        terms["refuted"] = excess.detach()
    if network.parameterisation in LEARNED_BOUNDARY and boundary_mask is not None and boundary_mask.any():
        gap = v[boundary_mask] - network.system.boundary_value(x[boundary_mask])
        boundary = gap.abs().mean() if weights.norm == "l1" else gap.square().mean()
        total = total + weights.boundary * boundary
        terms["boundary"] = boundary.detach()
    terms["loss"] = total.detach()
    return total, terms
