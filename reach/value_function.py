"""The value-function interface that grid solutions and neural networks both implement.

Safety code (policies, filters, rollouts, verification) takes any :class:`ValueFunction`, so a grid
solution can stand in for a learned network as the reference policy or a control experiment.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import torch

if TYPE_CHECKING:  # reach.systems re-exports this module's protocol
    from reach.systems.base import ControlAffineSystem


@runtime_checkable
class ValueFunction(Protocol):
    """``V(x, t)`` of a system, with ``t`` the time-to-go; batched over leading dimensions.

    ``value(x, t)`` maps states ``(..., n)`` to ``(...)`` and ``gradient(x, t)`` to ``(..., n)``;
    ``t`` is a float or a tensor broadcastable to the batch. Both run on ``x``'s device and dtype.
    """

    system: ControlAffineSystem

    def value(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor: ...

    def gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor: ...


def time_range(vf: object) -> tuple[float, float] | None:
    """The times-to-go ``(low, high)`` a value function can be trusted at, or None if it does not say.

    Networks are trained on ``[0, horizon]`` and grid solutions store a range of times; outside it a
    network extrapolates and a grid cannot interpolate, so both refuse such times."""
    rng = getattr(vf, "time_range", None)
    return None if rng is None else (float(rng[0]), float(rng[1]))


def check_time(t: float | torch.Tensor, low: float, high: float) -> None:
    """Raise ``ValueError`` unless every time-to-go in ``t`` is finite and in ``[low, high]``.

    A relative tolerance of 1e-6 admits times computed in float32 (``k * dt`` summed up)."""
    tt = torch.as_tensor(t, dtype=torch.float64)
    tol = 1e-6 * max(1.0, abs(high))
    bad = ~torch.isfinite(tt) | (tt < low - tol) | (tt > high + tol)
    if bool(bad.any()):
        value = tt[bad].reshape(-1)[0].item() if tt.ndim else tt.item()
        raise ValueError(
            f"time-to-go t = {value} lies outside [{low:g}, {high:g}], the times this value function covers "
            "(networks are trained on [0, horizon]; grid solutions store a range of times)"
        )


def check_time_coverage(vf: object, low: float, high: float, what: str) -> None:
    """Raise before any work if ``vf`` does not cover the times-to-go ``[low, high]`` that ``what`` needs."""
    rng = time_range(vf)
    if rng is None:
        return
    tol = 1e-6 * max(1.0, abs(high))
    if low < rng[0] - tol or high > rng[1] + tol:
        raise ValueError(
            f"{what} needs times-to-go [{low:g}, {high:g}], but the value function covers only [{rng[0]:g}, {rng[1]:g}]"
            + (" (solve the grid with --times from 0, e.g. the default of reach groundtruth)" if rng[0] > low else "")
        )


def value_and_gradient(
    vf: ValueFunction, x: torch.Tensor, t: float | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(V(x, t), dV/dx)`` with one network pass where ``vf`` offers ``value_and_gradient``."""
    fused = getattr(vf, "value_and_gradient", None)
    if fused is not None:
        return fused(x, t)
    return vf.value(x, t), vf.gradient(x, t)


class MinimumOf:
    """``V(x, t) = min_k V_k(x, t)``: the pointwise minimum of value functions of one system's physics.

    **Why.** Where a member is an *upper bound* on the true value, capping a learned network with it
    can only help: if ``V_true <= U`` then ``|min(V_net, U) - V_true| <= |V_net - V_true|`` at every
    state, and ``{min(V_net, U) <= 0}`` contains ``{U <= 0}``. The cooperative three-car system is
    the example: a pair of cars that ignores the third can only do better, so the union of pairwise
    BRTs (:class:`~groundtruth.pairwise.PairwiseUnion`) bounds its value from above, and
    ``MinimumOf(network, union)`` misses none of the union's unsafe states.

    **Gradient.** By default the minimising member's (a subgradient where two tie): the induced
    policy switches to the bound's optimal inputs where the bound is active. :meth:`active` says
    where that is. ``steer_by=k`` returns member ``k``'s gradient everywhere instead, so the value is
    capped while the policy stays member ``k``'s. That is what a bound such as the union of pairwise
    BRTs calls for: its gradient steers only the closest pair and leaves the third car driving
    straight, which a filter's backup rollout pays for (docs: Verification, capping a 9D network).
    The capped value and member ``k``'s gradient then disagree where the bound is active; a filter
    that reads both (the smooth filter's barrier condition) treats the bound's value as a level
    there, not as a function to descend.

    Members must share the physics (:meth:`~reach.systems.base.ControlAffineSystem.same_physics`);
    the composition's ``system`` is the first member's, and its ``time_range`` the times every
    member covers.
    """

    def __init__(
        self, *members: ValueFunction, labels: tuple[str, ...] | None = None, steer_by: int | None = None
    ) -> None:
        if len(members) < 2:
            raise ValueError(f"MinimumOf needs at least two value functions, got {len(members)}")
        for k, member in enumerate(members):
            if not isinstance(member, ValueFunction):
                raise ValueError(f"MinimumOf: member {k} is not a value function ({type(member).__name__})")
            if k:
                members[0].system.require_same_physics(member.system, f"MinimumOf member {k}")
        if labels is not None and len(labels) != len(members):
            raise ValueError(f"MinimumOf: {len(labels)} labels for {len(members)} members")
        if steer_by is not None and (
            isinstance(steer_by, bool) or not isinstance(steer_by, int) or not 0 <= steer_by < len(members)
        ):
            raise ValueError(f"MinimumOf: steer_by must be a member index in [0, {len(members) - 1}], got {steer_by!r}")
        self.members = tuple(members)
        self.labels = labels
        self.steer_by = steer_by
        self.system = members[0].system
        ranges = [r for r in (time_range(m) for m in members) if r is not None]
        self.time_range = (max(r[0] for r in ranges), min(r[1] for r in ranges)) if ranges else None
        if self.time_range is not None and self.time_range[0] > self.time_range[1]:
            raise ValueError(f"MinimumOf: the members share no time-to-go ({ranges})")

    def _check(self, t: float | torch.Tensor) -> None:
        if self.time_range is not None:
            check_time(t, *self.time_range)

    def value(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        self._check(t)
        return torch.stack([m.value(x, t) for m in self.members], dim=-1).min(dim=-1).values

    def value_and_gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        self._check(t)
        if self.steer_by is not None:  # the others' values only: no gradient of the bound is taken
            k = self.steer_by
            value, grad = value_and_gradient(self.members[k], x, t)
            others = [m.value(x, t) for j, m in enumerate(self.members) if j != k]
            return torch.stack([value, *others], dim=-1).min(dim=-1).values, grad
        both = [value_and_gradient(m, x, t) for m in self.members]
        values = torch.stack([v for v, _ in both], dim=-1)
        best = values.argmin(dim=-1, keepdim=True)
        grads = torch.stack([g for _, g in both], dim=-2)
        index = best.unsqueeze(-1).expand(*best.shape[:-1], 1, grads.shape[-1])
        return values.gather(-1, best).squeeze(-1), grads.gather(-2, index).squeeze(-2)

    def gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        return self.value_and_gradient(x, t)[1]

    def active(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """Index of the minimising member at each state, ``(...)`` (ties go to the first)."""
        self._check(t)
        return torch.stack([m.value(x, t) for m in self.members], dim=-1).argmin(dim=-1)
