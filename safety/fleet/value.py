"""The value of a fleet of Dubins cars from its pairs: one two-car problem serves every pair of its kind.

A fleet is a :class:`~reach.systems.MultiVehicle` of tens of cars. Its pairwise value is
``min over failure pairs (i, j) of V_ij(relative state of j in i's frame, t)``, the value of
:class:`~groundtruth.pairwise.PairwiseUnion`, but a fleet cannot afford every pair: at 64 cars there
are 2,016, and all but a few dozen are far apart. :class:`FleetValue` evaluates only the pairs that
can matter (the *distance cull*) and returns them as flat tensors, batched over states and pairs,
with what a filter needs to linearise each pair's value over one step.

**The distance cull.** Turning only rotates the relative position, so the distance between two
cars falls at most at ``v_i + v_j``; a pair at margin ``l = |p_i - p_j| - R`` cannot collide within
the time-to-go ``t`` unless ``l <= (v_i + v_j) t``, and its value obeys
``V_ij(t) >= l - (v_i + v_j) t``. A filter reads pair values only up to some level (its threshold
plus activation band); a pair farther apart than ``R + (v_i + v_j) t + level``
(:meth:`FleetValue.cull_distance`) has ``V_ij > level`` and is never read, so it is not evaluated.
The bound is one of the true value; the test suite checks it on the shipped pair grid on random
states (a grid reads relative positions beyond its box as the edge value, an under-statement,
so a pair just inside the cull distance may read lower than it is: a conservative error).

**Kinds.** Cars of equal speed, turn bound and role form a kind; a pair problem
(:class:`~reach.systems.RelativePair`) serves every pair whose frame car (a control car) and other
car have its physics, matched by :meth:`~reach.systems.base.ControlAffineSystem.physics_config` as
:class:`PairwiseUnion` matches them. Where two control cars of different kinds meet and only the
problem with the other car as frame car is given, that one serves with the roles swapped.
Evaluation loops over the handful of pair problems, never over pairs or states.

**One step, linearised.** With ``g = grad V_ij`` at relative state ``r``, the relative dynamics
``r' = f(r) + w_i (r_1, -r_0, -1) + w_j (0, 0, 1)`` are affine in the two turn rates, so
``dV_ij/dt = a + b_i w_i + b_j w_j`` with ``a = g . f(r)`` (where car ``j`` is a disturbance, its
worst turn rate is folded into ``a`` and ``b_j = 0``), ``b_i = g_0 r_1 - g_1 r_0 - g_2`` and
``b_j = g_2``: the heading components of the full-state gradient
(:func:`~groundtruth.pairwise.pull_back`). The time-to-go is held fixed (the fleet filter uses the
pair problem as time-invariant, ``t`` at its horizon).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from groundtruth.pairwise import relative_state
from groundtruth.solution import GridSolution
from reach.systems import MultiVehicle, RelativePair
from reach.value_function import value_and_gradient

__all__ = ["FleetValue", "PairCandidates", "check_fleet_state", "check_present"]


@dataclass(frozen=True)
class PairCandidates:
    """The pairs a fleet value evaluated, flat over states and pairs (``P`` of them).

    Attributes:
        batch, first, second: ``(P,)`` long: the state, the frame car (a control car) and the other car.
        rel: ``(P, 3)`` the relative state of ``second`` in ``first``'s frame.
        value, gradient: ``(P,)`` and ``(P, 3)``: the pair value and its gradient in relative coordinates.
        drift, switch_first, switch_second: ``(P,)``: ``dV/dt = drift + switch_first w_first +
            switch_second w_second`` (module docstring; ``switch_second`` is 0 where ``second`` is a
            disturbance car, whose worst turn rate ``drift`` already holds).
        speed_sum: ``(P,)`` ``v_first + v_second``.
        cull_bound: ``(B,)`` the least ``l - (v_i + v_j) t`` over the failure pairs present but not
            evaluated (``+inf`` where there are none): a lower bound of their values.
    """

    batch: torch.Tensor
    first: torch.Tensor
    second: torch.Tensor
    rel: torch.Tensor
    value: torch.Tensor
    gradient: torch.Tensor
    drift: torch.Tensor
    switch_first: torch.Tensor
    switch_second: torch.Tensor
    speed_sum: torch.Tensor
    cull_bound: torch.Tensor

    @property
    def count(self) -> int:
        """How many pairs were evaluated."""
        return int(self.batch.shape[0])


def check_fleet_state(x: object, n: int) -> torch.Tensor:
    """``x`` if it is a floating ``(B, 3 n)`` tensor of finite numbers, else ``ValueError`` naming it."""
    if not isinstance(x, torch.Tensor) or not x.dtype.is_floating_point:
        kind = x.dtype if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"fleet states must be a floating-point torch tensor, got {kind}")
    if x.ndim != 2 or x.shape[1] != 3 * n:
        raise ValueError(f"fleet states must have shape (B, {3 * n}), got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"fleet states contain NaN or inf, e.g. state {x[~torch.isfinite(x).all(-1)][0].tolist()}")
    return x


def check_present(present: object, batch: int, n: int, device: torch.device) -> torch.Tensor:
    """``present`` as a bool ``(B, n)`` tensor (``None``: every car present); else ``ValueError``."""
    if present is None:
        return torch.ones(batch, n, dtype=torch.bool, device=device)
    if not isinstance(present, torch.Tensor) or present.dtype != torch.bool:
        kind = present.dtype if isinstance(present, torch.Tensor) else type(present).__name__
        raise ValueError(f"present must be a bool torch tensor, got {kind}")
    if tuple(present.shape) != (batch, n):
        raise ValueError(f"present must have shape {(batch, n)}, got {tuple(present.shape)}")
    return present


def _check_time(t: object) -> float:
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0:
        raise ValueError(f"the time-to-go t must be a finite number >= 0, got {t!r}")
    return float(t)


class FleetValue:
    """The pairwise value of a fleet, evaluated on the pairs that can matter (module docstring).

    Args:
        system: the fleet, a :class:`~reach.systems.MultiVehicle` of any number of cars.
        solutions: the pair problems' value functions: one (a :class:`GridSolution` of a
            :class:`~reach.systems.RelativePair`, or any value function of one with ``value`` and
            ``gradient``), or several, one per pair kind. Each failure pair must find one; the
            first that matches serves. A grid solution reads positions beyond its box as the edge
            value (``outside="clamp"``, as :class:`~groundtruth.pairwise.PairwiseUnion` sets it).
    """

    def __init__(self, system: MultiVehicle, solutions: object) -> None:
        if not isinstance(system, MultiVehicle):
            raise ValueError(f"FleetValue needs a MultiVehicle fleet, got {getattr(system, 'name', system)!r}")
        sols = list(solutions.values()) if isinstance(solutions, dict) else solutions
        sols = list(sols) if isinstance(sols, (list, tuple)) else [sols]
        for s in sols:
            if not isinstance(getattr(s, "system", None), RelativePair):
                raise ValueError(f"FleetValue needs value functions of a RelativePair, got {type(s).__name__}")
            if isinstance(s, GridSolution):
                s.outside = "clamp"
        self.system = system
        self.solutions = sols
        n = system.num_cars
        cars = system.cars
        self.speeds = torch.tensor([c.speed for c in cars], dtype=torch.float64)
        self.turn_bounds = torch.tensor([c.max_turn_rate for c in cars], dtype=torch.float64)
        self.control = torch.tensor([c.role == "control" for c in cars])
        self.collision_radius = system.collision_radius
        self.horizon = min(float(s.time_range[1]) if hasattr(s, "time_range") else s.system.horizon for s in sols)
        self._first, self._second, self._kind = self._resolve_kinds()
        upper = torch.triu(torch.ones(n, n, dtype=torch.bool), diagonal=1)
        self._failure = upper & (self.control[:, None] | self.control[None, :])
        self.speed_sum = self.speeds[:, None] + self.speeds[None, :]

    # ------------------------------------------------------------------ set-up
    def _resolve_kinds(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(N, N)`` tables for ``i < j``: the frame car, the other car, the solution index.

        Built over car kinds (a handful), then looked up for every pair at once."""
        cars = self.system.cars
        kinds = sorted({(c.speed, c.max_turn_rate, c.role) for c in cars})
        car_kind = torch.tensor([kinds.index((c.speed, c.max_turn_rate, c.role)) for c in cars])
        table = torch.full((len(kinds), len(kinds)), -1, dtype=torch.long)
        for a, (va, wa, ra) in enumerate(kinds):
            for b, (vb, wb, rb) in enumerate(kinds):
                if ra != "control":
                    continue
                wanted = RelativePair(va, vb, wa, wb, rb, self.system.collision_radius).physics_config()
                match = [k for k, s in enumerate(self.solutions) if s.system.physics_config() == wanted]
                table[a, b] = match[0] if match else -1
        n = len(cars)
        idx = torch.arange(n)
        i, j = idx[:, None].expand(n, n), idx[None, :].expand(n, n)
        first = torch.where(self.control[:, None], i, j)  # the frame car must be a control car
        second = torch.where(self.control[:, None], j, i)
        kind = table[car_kind[first], car_kind[second]]
        swap = (kind < 0) & self.control[second] & (table[car_kind[second], car_kind[first]] >= 0)
        first, second = torch.where(swap, second, first), torch.where(swap, first, second)
        kind = table[car_kind[first], car_kind[second]]
        need = torch.triu(torch.ones(n, n, dtype=torch.bool), 1) & (self.control[:, None] | self.control[None, :])
        missing = need & (kind < 0)
        if bool(missing.any()):
            a, b = (int(v) for v in torch.nonzero(missing)[0])
            have = [s.system.config() for s in self.solutions]
            raise ValueError(f"no pair solution for cars ({a}, {b}) ({cars[a]}, {cars[b]}); have {have}")
        return first, second, kind

    @property
    def num_cars(self) -> int:
        return self.system.num_cars

    @property
    def pair_kind(self) -> torch.Tensor:
        """``(N, N)`` symmetric: the index into :attr:`solutions` serving each failure pair, ``-1``
        on the diagonal and for pairs that are not failure pairs (two disturbance cars)."""
        upper = torch.where(self._failure, self._kind, -1)
        return torch.maximum(upper, upper.T)

    def cull_distance(self, t: float, level: float | torch.Tensor = 0.0) -> torch.Tensor:
        """``(N, N)``: ``R + (v_i + v_j) t + level``, the distance beyond which a pair's value exceeds
        ``level`` (a float, or an ``(N, N)`` tensor of levels per pair)."""
        return self.collision_radius + self.speed_sum * _check_time(t) + torch.as_tensor(level, dtype=torch.float64)

    # ------------------------------------------------------------------ evaluation
    def candidates(
        self,
        x: torch.Tensor,
        t: float,
        present: torch.Tensor | None = None,
        level: float | torch.Tensor = 0.0,
    ) -> PairCandidates:
        """The failure pairs of present cars closer than :meth:`cull_distance` (``level``: the
        highest value the caller reads), with their values and linearisations, ordered by
        ``(batch, i, j)`` with ``i < j`` the car indices."""
        n = self.num_cars
        x = check_fleet_state(x, n)
        t = _check_time(t)
        present = check_present(present, x.shape[0], n, x.device)
        pos = x[:, : 2 * n].reshape(-1, n, 2)
        dist = torch.cdist(pos, pos)  # (B, N, N)
        live = self._failure.to(x.device) & present[:, :, None] & present[:, None, :]
        cull = self.cull_distance(t, level).to(x.device, x.dtype)
        near = live & (dist < cull)
        margin = dist - self.collision_radius - self.speed_sum.to(x.device, x.dtype) * t
        far = torch.where(live & ~near, margin, torch.full_like(margin, math.inf))
        cull_bound = far.flatten(1).min(-1).values if n > 1 else x.new_full((x.shape[0],), math.inf)
        b, i, j = torch.nonzero(near, as_tuple=True)
        first, second = self._first.to(x.device)[i, j], self._second.to(x.device)[i, j]
        kind = self._kind.to(x.device)[i, j]
        th = x[:, 2 * n :]
        rel = relative_state(pos[b, first], pos[b, second], th[b, first], th[b, second])
        value, grad = self._evaluate(rel, t, kind)
        if not (bool(torch.isfinite(value).all()) and bool(torch.isfinite(grad).all())):
            bad = ~(torch.isfinite(value) & torch.isfinite(grad).all(-1))
            k = int(torch.nonzero(bad)[0])
            raise ValueError(
                f"the pair value function returned a non-finite value or gradient for cars "
                f"({int(first[k])}, {int(second[k])}) of state {int(b[k])} (relative state {rel[k].tolist()}, t = {t})"
            )
        drift, s_first, s_second = self._linearise(rel, grad, first, second)
        return PairCandidates(
            b, first, second, rel, value, grad, drift, s_first, s_second, self.speed_sum.to(x.device)[i, j], cull_bound
        )

    def _evaluate(self, rel: torch.Tensor, t: float, kind: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Values and gradients of each pair at its relative state, one call per pair problem."""
        if len(self.solutions) == 1:
            return self._call(self.solutions[0], rel, t)
        value = rel.new_empty(rel.shape[0])
        grad = rel.new_empty(rel.shape)
        for k, sol in enumerate(self.solutions):  # a handful of pair kinds
            rows = kind == k
            if bool(rows.any()):
                value[rows], grad[rows] = self._call(sol, rel[rows], t)
        return value, grad

    @staticmethod
    def _call(sol: object, rel: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor]:
        if not isinstance(sol, GridSolution):  # a network: keep it on the box it was trained on
            box = sol.system.half_width
            rel = torch.cat([rel[:, :2].clamp(-box, box), rel[:, 2:]], dim=-1)
        return value_and_gradient(sol, rel, t)

    def _linearise(
        self, rel: torch.Tensor, grad: torch.Tensor, first: torch.Tensor, second: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(a, b_first, b_second)`` of ``dV/dt = a + b_first w_first + b_second w_second``."""
        dev, dt = rel.device, rel.dtype
        v1, v2 = self.speeds.to(dev, dt)[first], self.speeds.to(dev, dt)[second]
        g0, g1, g2 = grad[:, 0], grad[:, 1], grad[:, 2]
        drift = g0 * (-v1 + v2 * torch.cos(rel[:, 2])) + g1 * (v2 * torch.sin(rel[:, 2]))
        s_first = g0 * rel[:, 1] - g1 * rel[:, 0] - g2  # as groundtruth.pairwise.pull_back writes it
        controlled = self.control.to(dev)[second]
        worst = -self.turn_bounds.to(dev, dt)[second] * g2.abs()  # a disturbance car's worst turn
        return drift + torch.where(controlled, 0.0, worst), s_first, torch.where(controlled, g2, 0.0)

    def value(
        self, x: torch.Tensor, t: float, present: torch.Tensor | None = None, level: float | torch.Tensor = 0.0
    ) -> torch.Tensor:
        """``(B,)``: the least pair value, over the evaluated pairs and the culled pairs' lower bound
        (:attr:`PairCandidates.cull_bound`): a lower bound of the fleet's pairwise value that equals
        it wherever it is at most ``level``; ``+inf`` where no pair of present cars exists."""
        c = self.candidates(x, t, present, level)
        low = c.cull_bound.clone()
        return low.scatter_reduce(0, c.batch, c.value, reduce="amin")

    def pair_values(
        self, x: torch.Tensor, t: float, present: torch.Tensor | None = None, level: float | torch.Tensor = 0.0
    ) -> torch.Tensor:
        """``(B, N, N)`` symmetric: each evaluated pair's value at ``[b, i, j]`` and ``[b, j, i]``,
        ``+inf`` for the pairs not evaluated (culled, absent, or no failure pair)."""
        c = self.candidates(x, t, present, level)
        n = self.num_cars
        out = x.new_full((x.shape[0], n, n), math.inf)
        out[c.batch, c.first, c.second] = c.value
        out[c.batch, c.second, c.first] = c.value
        return out
