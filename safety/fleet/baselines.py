"""Two baselines for the fleet filter, with its interface: ``f(x, t, u_nominal, present) -> (u, FleetInfo)``.

* :class:`NaiveUnionSwitch`: the switch filter on the union of pairwise values
  (:class:`~groundtruth.pairwise.PairwiseUnion`), batched over a fleet. Where some pair's value is
  at or below its threshold, every control car takes ``u*`` of the union's gradient, the gradient
  of the least pair alone: that pair's two cars turn by the signs of their switching functions and
  every other car gets 0 (drives straight), as ``optimal_control`` breaks a zero switching function.
  It answers one pair and can steer into another. With one threshold for every pair it equals
  ``SafetyFilter(PairwiseUnion(system, pair), threshold, policy="gradient")`` (tested at 3 and 4 cars).
* :class:`DistanceCBF`: the common distance-based CBF-QP, ``h = |p_i - p_j|^2 - R^2`` with the
  discrete condition ``h(next) >= (1 - gamma) h`` over one held step of ``dt``. A turn rate moves a
  car's position only at second order in the step (``p(dt) = p + v dt e + v w dt^2 / 2 e_perp +
  O(dt^3)``, ``e_perp`` the heading turned left), so ``h(next)`` is linearised in the turn rates
  around straight driving: ``h_0 + dt^2 (d_0 . v_j e_perp_j) w_j - dt^2 (d_0 . v_i e_perp_i) w_i``,
  with ``d_0`` the offset after a straight step. Pairs within ``R + (v_i + v_j) sensing_time``
  are sensed; groups with a sensed pair whose condition the nominal inputs break are solved by the
  same QP and fallback as the fleet filter (:func:`~safety.fleet.filter.qp_conflicts`), every
  conflict in one call; the rest keep their nominal inputs, which is the QP's own answer there (the
  groups decouple). For unicycles at constant speed the distance is no valid barrier (the turn rate
  barely moves ``h`` over a step): that is what it measures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from reach.validation import check_float, positive_finite
from safety.fleet.filter import (
    FleetFilterSettings,
    FleetInfo,
    PairRows,
    checked_inputs,
    fallback_inputs,
    pair_thresholds,
    qp_conflicts,
    with_signs,
)
from safety.fleet.graph import conflicts
from safety.fleet.value import FleetValue

__all__ = ["CBFSettings", "DistanceCBF", "NaiveUnionSwitch"]


class NaiveUnionSwitch:
    """The switch filter on the union of pairwise values, for a fleet (module docstring).

    Args:
        fleet_value: the fleet's pairwise value.
        settings: ``dt`` and ``threshold`` as for :class:`~safety.fleet.filter.FleetFilter` (the
            default threshold per pair kind; the band and QP options are unused).
    """

    def __init__(self, fleet_value: FleetValue, settings: FleetFilterSettings) -> None:
        self.fleet_value = fleet_value
        self.settings = settings
        self.threshold = pair_thresholds(fleet_value, settings)

    def __call__(
        self, x: torch.Tensor, t: float, u_nominal: torch.Tensor, present: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, FleetInfo]:
        fv = self.fleet_value
        n = fv.num_cars
        x, present, given = checked_inputs(fv, x, u_nominal, present)
        batch = x.shape[0]
        c = fv.candidates(x, t, present, self.threshold)
        dev, dt = x.device, x.dtype
        threatened = c.value <= self.threshold.to(dev, dt)[c.first, c.second]
        trigger = torch.zeros(batch, dtype=torch.bool, device=dev)
        trigger[c.batch[threatened]] = True
        # the least pair of each state (the first in (i, j) order on a tie, as argmin over the union's pairs)
        low = torch.full((batch,), math.inf, dtype=dt, device=dev).scatter_reduce(0, c.batch, c.value, reduce="amin")
        order = torch.arange(c.count, device=dev)
        at_min = c.value == low[c.batch]
        pick = torch.full((batch,), c.count, device=dev).scatter_reduce(
            0, c.batch[at_min], order[at_min], reduce="amin"
        )
        best = pick[trigger]
        sign, has = fallback_inputs(c, best, c.value, n, batch)
        wmax = fv.turn_bounds.to(dev, dt).repeat(batch)
        backup = torch.where(has, wmax * sign, 0.0).reshape(batch, n)
        intervened = trigger[:, None] & fv.control.to(dev)[None, :] & present
        u = torch.where(intervened, backup.to(given.dtype), given)
        min_value = torch.minimum(low, c.cull_bound)
        count = trigger.long()
        info = FleetInfo(
            intervened, count, torch.zeros_like(count), torch.zeros_like(count), c.count, min_value, given, u
        )
        return u, info


@dataclass(frozen=True)
class CBFSettings:
    """The distance CBF-QP's options.

    Attributes:
        dt: the control period (s).
        gamma: the discrete barrier rate in ``(0, 1]``: ``h(next) >= (1 - gamma) h``.
        sensing_time: pairs within ``R + (v_i + v_j) sensing_time`` enter the QP (s).
        penalty, slack_tolerance: the QP's slack price and infeasibility tolerance
            (:class:`~safety.fleet.filter.FleetFilterSettings`).
    """

    dt: float
    gamma: float = 0.5
    sensing_time: float = 1.0
    penalty: float = 1e3
    slack_tolerance: float = 1e-6

    def __post_init__(self) -> None:
        object.__setattr__(self, "dt", positive_finite("dt", self.dt))
        gamma = check_float("gamma", self.gamma, 0)
        if not 0 < gamma <= 1:
            raise ValueError(f"gamma must lie in (0, 1], got {self.gamma!r}")
        object.__setattr__(self, "gamma", gamma)
        for name in ("sensing_time", "penalty", "slack_tolerance"):
            object.__setattr__(self, name, positive_finite(name, getattr(self, name)))


class DistanceCBF:
    """The distance-based CBF-QP baseline (module docstring).

    Args:
        fleet_value: the fleet (only its cars are read: speeds, turn bounds, roles, radius).
        settings: :class:`CBFSettings`.
    """

    def __init__(self, fleet_value: FleetValue, settings: CBFSettings) -> None:
        if not isinstance(settings, CBFSettings):
            raise ValueError(f"settings must be a CBFSettings, got {type(settings).__name__}")
        self.fleet_value = fleet_value
        self.settings = settings

    def __call__(
        self, x: torch.Tensor, t: float, u_nominal: torch.Tensor, present: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, FleetInfo]:
        fv = self.fleet_value
        n = fv.num_cars
        x, present, given = checked_inputs(fv, x, u_nominal, present)
        batch = x.shape[0]
        dev, dt = x.device, x.dtype
        step, gamma = self.settings.dt, self.settings.gamma
        pos = x[:, : 2 * n].reshape(batch, n, 2)
        th = x[:, 2 * n :]
        speed = fv.speeds.to(dev, dt)
        dist = torch.cdist(pos, pos)
        live = fv._failure.to(dev) & present[:, :, None] & present[:, None, :]
        sensed = live & (dist < fv.collision_radius + fv.speed_sum.to(dev, dt) * self.settings.sensing_time)
        b, i, j = torch.nonzero(sensed, as_tuple=True)
        heading = torch.stack([torch.cos(th), torch.sin(th)], -1)  # (B, N, 2)
        left = torch.stack([-torch.sin(th), torch.cos(th)], -1)
        ahead = pos + step * speed[None, :, None] * heading
        d0 = ahead[b, j] - ahead[b, i]
        h = ((pos[b, j] - pos[b, i]) ** 2).sum(-1) - fv.collision_radius**2
        h0 = (d0**2).sum(-1) - fv.collision_radius**2
        c_i = -(step**2) * speed[i] * (d0 * left[b, i]).sum(-1)
        c_j = (step**2) * speed[j] * (d0 * left[b, j]).sum(-1)
        control = fv.control.to(dev)
        wmax_car = fv.turn_bounds.to(dev, dt)
        # a car the filter does not steer: its worst turn rate, on the right-hand side
        worst = torch.where(control[i], 0.0, wmax_car[i] * c_i.abs()) + torch.where(
            control[j], 0.0, wmax_car[j] * c_j.abs()
        )
        c_i, c_j = torch.where(control[i], c_i, 0.0), torch.where(control[j], c_j, 0.0)
        rhs = (1 - gamma) * h - h0 + worst
        nominal = given.to(dt)
        broken = c_i * nominal[b, i] + c_j * nominal[b, j] < rhs
        pairs = PairRows(b, i, j, c_i, c_j)
        g = conflicts(batch, n, (b, i, j), broken)
        edges = torch.nonzero(g.in_conflict).squeeze(-1)
        wmax = wmax_car.repeat(batch)
        cars = (wmax, control.repeat(batch))
        conditions = (torch.stack([c_i, c_j], -1)[edges], rhs[edges])
        out, solved, infeasible, fallen = qp_conflicts(
            pairs, edges, g.edge_label[edges], conditions, nominal, cars, self.settings
        )
        out = with_signs(out, fallback_inputs(pairs, fallen, h, n, batch), cars)
        intervened = g.car_in_conflict & control
        u = torch.where(intervened, out.to(given.dtype), given)
        low = torch.full((batch,), math.inf, dtype=dt, device=dev).scatter_reduce(0, b, h, reduce="amin")
        info = FleetInfo(intervened, g.count, solved, infeasible, int(b.numel()), low, given, u)
        return u, info
