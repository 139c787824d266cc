"""The fleet filter: every threatened pair of a fleet answered at once, from pairwise HJ values.

``FleetFilter(FleetValue(system, pair_solution), FleetFilterSettings(dt=0.05))(x, t, u_nominal,
present) -> (u, FleetInfo)``, batched over states ``x: (B, 3N)`` (:class:`~reach.systems.MultiVehicle`
order), nominal turn rates ``u_nominal: (B, N)`` and presence masks ``present: (B, N)`` (cars that
left the scene take part in no pair). The rule, per state:

1. Each pair ``(i, j)`` of present cars has a value ``V_ij`` (:class:`~safety.fleet.value.FleetValue`,
   culled by distance), a threshold ``theta_ij`` (default: the larger of the switch filter's default
   for the pair problem at the filter's ``dt``, :func:`~safety.filters.settings.default_threshold`,
   and ``reaction_time`` seconds of the pair's closing speed, :data:`REACTION_TIME` by default) and an
   activation band ``band_ij`` (default ``dt (v_i + v_j)``, what ``V`` can lose in one held step).
   It is *active* where ``V_ij <= theta_ij + band_ij`` and *threatened* where ``V_ij <= theta_ij``.
2. Active pairs join cars into groups (:mod:`safety.fleet.graph`); a group with a threatened pair is
   a *conflict*. Cars outside conflicts keep their nominal input.
3. A conflict of one active pair takes the switch filter's rule: both cars apply the policy's input
   for the pair. ``policy="greedy"`` (default): the held input that leaves the pair's value highest
   after a short step (:mod:`safety.fleet.greedy`), which commits a head-on pair to one manoeuvre
   where the gradient's blend turns the two cars to the same side. ``policy="gradient"``: the pair's
   ``u*`` (0 where a switching function is 0, as
   :meth:`~reach.systems.base.ControlAffineSystem.optimal_control` breaks ties); at two cars the fleet
   filter is then ``SafetyFilter(PairwiseUnion(system, pair), threshold=theta, policy="gradient")``,
   to the bit (tested).
4. A conflict of several active pairs chooses its cars' turn rates together: the closest to the
   nominal ones such that every active pair's value, linearised over one step of ``dt``, stays at
   its threshold, ``V + dt (a + b_i w_i + b_j w_j) >= theta`` (:class:`~safety.fleet.value.PairCandidates`;
   a disturbance car's worst turn rate is in ``a``), within the turn bounds. Every such conflict of
   the batch is one block of one sparse QP, solved in one call (:mod:`safety.fleet.qp`).
5. Where a conflict's conditions cannot all be met (a positive slack), the fallback: the policy's
   input for the conflict (greedy: the joint held input that leaves its least pair value highest;
   gradient: each car on the ``u*`` of its worst active pair). It is counted in ``FleetInfo.infeasible``.

Fail closed: non-finite or misshapen states, nominal inputs, values or gradients raise ``ValueError``
naming them. A nominal input beyond a car's turn bound is clipped to it first, as
:class:`~safety.filters.base.SafetyFilter` does (it cannot be applied, so it is neither judged nor
kept as given). Unlike :class:`SafetyFilter` there is no domain box: a fleet roams its arena, and a
pair's relative state beyond its grid's box reads the edge value (conservative, :mod:`safety.fleet.value`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from reach.validation import check_float, positive_finite
from safety.filters.settings import default_threshold
from safety.fleet.graph import Conflicts, conflicts
from safety.fleet.greedy import HOLD, TIE_BREAKS, joint_greedy
from safety.fleet.qp import ConflictQP, solve
from safety.fleet.value import FleetValue, PairCandidates, check_fleet_state, check_present

#: seconds of closing speed (``v_i + v_j``) the default threshold keeps in hand, at least: a fleet's
#: pair reacts earlier than the switch filter's one-step default (``2 (v_i + v_j) dt``), as its
#: cars may be busy with other pairs (measured against the one-step default: docs/results/fleets.md)
REACTION_TIME = 0.5

#: the fleet filter's rules for a lone pair and an infeasible conflict (FleetFilterSettings.policy)
FLEET_POLICIES = ("greedy", "gradient")

__all__ = [
    "FLEET_POLICIES",
    "FleetFilter",
    "FleetFilterSettings",
    "FleetInfo",
    "PairRows",
    "check_nominal",
    "checked_inputs",
    "fallback_inputs",
    "pair_thresholds",
    "qp_conflicts",
    "solve_conflicts",
    "with_signs",
]


@dataclass(frozen=True)
class FleetFilterSettings:
    """How the fleet filter decides (module docstring).

    Attributes:
        dt: the control period (s): one held step the conditions look over.
        threshold: ``theta`` for every pair (>= 0); ``None``: per pair, the larger of the switch
            filter's default at ``dt`` (``2 (v_i + v_j) dt``) and ``REACTION_TIME (v_i + v_j)``.
        band: the activation band above the threshold (>= 0); ``None``: ``dt (v_i + v_j)`` per pair.
        penalty: the L1 price of a slack in the QP (:mod:`safety.fleet.qp`).
        slack_tolerance: a slack above this (unit-scaled rows) marks a conflict infeasible.
        gamma: the QP condition's discrete rate in ``(0, 1]``: ``V(next) - theta >= (1 - gamma)
            (V - theta)``, linearised. 1 (default) is the rule above, ``V(next) >= theta``; below 1
            a threatened pair need only recover part of its gap per step (and an active one may
            lose part of its room), which more conflicts can meet.
        policy: the input of a lone pair and of an infeasible conflict: ``"greedy"`` (default), the
            joint held input that leaves the conflict's least pair value highest
            (:mod:`safety.fleet.greedy`; a conflict of more than
            :data:`~safety.fleet.greedy.MAX_JOINT_CARS` cars weighs a few structured inputs), or
            ``"gradient"``, each car on its worst pair's ``u*`` (at two cars, the switch filter with
            ``policy="gradient"`` to the bit).
        hold: how long (s) the greedy policy holds each candidate input before it reads the pair
            values (:data:`~safety.fleet.greedy.HOLD` by default; its module says why).
        reaction_time: seconds of a pair's closing speed the default threshold keeps in hand, at
            least (>= 0; :data:`REACTION_TIME` by default). Longer makes pairs react earlier: fewer
            collisions where many cars converge, fewer cars home (measured: docs/results/fleets.md).
            Unused where ``threshold`` is given.
        tie_break: how the greedy policy chooses among held inputs whose least pair value ties
            (:data:`~safety.fleet.greedy.TIE_BREAKS`): ``"centre"`` (default), the first, all
            straight; ``"leximin"``, the one whose next least pair values are highest
            (:func:`~safety.fleet.greedy.leximin_best`; measured: docs/results/fleet_collisions.md).
    """

    dt: float
    threshold: float | None = None
    band: float | None = None
    penalty: float = 1e3
    slack_tolerance: float = 1e-6
    gamma: float = 1.0
    policy: str = "greedy"
    hold: float = HOLD
    reaction_time: float = REACTION_TIME
    tie_break: str = "centre"

    def __post_init__(self) -> None:
        object.__setattr__(self, "dt", positive_finite("dt", self.dt))
        object.__setattr__(self, "hold", positive_finite("hold", self.hold))
        object.__setattr__(self, "reaction_time", check_float("reaction_time", self.reaction_time, 0))
        if self.tie_break not in TIE_BREAKS:
            raise ValueError(f"tie_break must be one of {TIE_BREAKS}, got {self.tie_break!r}")
        if self.policy not in FLEET_POLICIES:
            raise ValueError(f"policy must be one of {FLEET_POLICIES}, got {self.policy!r}")
        gamma = check_float("gamma", self.gamma, 0)
        if not 0 < gamma <= 1:
            raise ValueError(f"gamma must lie in (0, 1], got {self.gamma!r}")
        object.__setattr__(self, "gamma", gamma)
        for name in ("threshold", "band"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, check_float(name, getattr(self, name), 0))
        object.__setattr__(self, "penalty", positive_finite("penalty", self.penalty))
        object.__setattr__(self, "slack_tolerance", positive_finite("slack_tolerance", self.slack_tolerance))


@dataclass
class FleetInfo:
    """What a fleet filter did, per state.

    Attributes:
        intervened: ``(B, N)`` cars whose nominal input was overridden (they were in a conflict).
        conflicts: ``(B,)`` conflicts; ``solved``: ``(B,)`` of them decided by the QP (two or more
            active pairs); ``infeasible``: ``(B,)`` of those that fell back (no input met every pair).
        pairs: pairs evaluated in the whole batch (after the distance cull).
        min_value: ``(B,)`` the least pair value (the culled pairs' bound where none is near).
        nominal, applied: ``(B, N)`` the nominal input (clipped to the turn bounds) and the input applied.
    """

    intervened: torch.Tensor
    conflicts: torch.Tensor
    solved: torch.Tensor
    infeasible: torch.Tensor
    pairs: int
    min_value: torch.Tensor
    nominal: torch.Tensor
    applied: torch.Tensor


def check_nominal(u: object, batch: int, bounds: torch.Tensor) -> torch.Tensor:
    """``u`` clipped to ``|u_k| <= bounds_k`` if it is a finite floating ``(B, N)`` tensor, else ``ValueError``."""
    n = bounds.shape[0]
    if not isinstance(u, torch.Tensor) or not u.dtype.is_floating_point:
        kind = u.dtype if isinstance(u, torch.Tensor) else type(u).__name__
        raise ValueError(f"u_nominal must be a floating-point torch tensor, got {kind}")
    if tuple(u.shape) != (batch, n):
        raise ValueError(f"u_nominal must have shape {(batch, n)}, got {tuple(u.shape)}")
    if not bool(torch.isfinite(u).all()):
        raise ValueError(f"u_nominal contains NaN or inf: {u[~torch.isfinite(u)][:4].tolist()}")
    w = bounds.to(u.device, u.dtype)
    return torch.minimum(torch.maximum(u, -w), w)


def checked_inputs(
    fv: FleetValue, x: torch.Tensor, u_nominal: torch.Tensor, present: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A fleet rule's call inputs checked (every rule of :mod:`safety.fleet` refuses alike):
    ``(x, present, nominal)``, the nominal input clipped to the turn bounds (:func:`check_nominal`)."""
    x = check_fleet_state(x, fv.num_cars)
    present = check_present(present, x.shape[0], fv.num_cars, x.device)
    return x, present, check_nominal(u_nominal, x.shape[0], fv.turn_bounds)


def pair_thresholds(fleet_value: FleetValue, settings: FleetFilterSettings) -> torch.Tensor:
    """``(N, N)`` each pair's threshold ``theta``: ``settings.threshold`` where given, else the larger
    of the switch filter's default for the pair problem at ``settings.dt`` and
    ``settings.reaction_time`` of the pair's closing speed (the module docstring says why)."""
    if not isinstance(fleet_value, FleetValue):
        raise ValueError(f"a fleet filter needs a FleetValue, got {type(fleet_value).__name__}")
    if not isinstance(settings, FleetFilterSettings):
        raise ValueError(f"settings must be a FleetFilterSettings, got {type(settings).__name__}")
    speed_sum = fleet_value.speed_sum
    if settings.threshold is not None:
        return torch.full_like(speed_sum, settings.threshold)
    per_kind = torch.tensor(
        [default_threshold(s.system, settings.dt) for s in fleet_value.solutions], dtype=torch.float64
    )
    # a pair must react earlier than a lone pair would: its cars may be busy with another pair when
    # it needs them, so the default holds reaction_time of closing speed in hand
    return torch.maximum(per_kind[fleet_value.pair_kind.clamp(min=0)], settings.reaction_time * speed_sum)


class PairRows(NamedTuple):
    """What a decision reads of its pairs, flat ``(P,)``: state, the two cars, and how a condition
    on the pair grows with each car's turn rate (``switch_second`` 0 for a car not controlled)."""

    batch: torch.Tensor
    first: torch.Tensor
    second: torch.Tensor
    switch_first: torch.Tensor
    switch_second: torch.Tensor


def fallback_inputs(
    c: PairRows | PairCandidates, edges: torch.Tensor, score: torch.Tensor, n: int, batch: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B * N,)`` the turn-rate sign each car of the pairs ``edges`` (indices into ``c``) takes
    from its worst pair (least ``score``; ties: the first), the sign of its switching function in
    that pair (the pair's optimal input, 0 on a tie as ``optimal_control`` breaks it), and a mask
    of those cars."""
    nodes = batch * n
    dev = score.device
    if edges.numel() == 0:
        return torch.zeros(nodes, dtype=score.dtype, device=dev), torch.zeros(nodes, dtype=torch.bool, device=dev)
    u = c.batch[edges] * n + c.first[edges]
    v = c.batch[edges] * n + c.second[edges]
    s = score[edges]
    worst = torch.full((nodes,), math.inf, dtype=s.dtype, device=dev)
    worst = worst.scatter_reduce(0, u, s, reduce="amin").scatter_reduce(0, v, s, reduce="amin")
    order = torch.arange(edges.numel(), device=dev)
    big = torch.full((nodes,), edges.numel(), dtype=torch.long, device=dev)
    pick = big.scatter_reduce(0, u[s == worst[u]], order[s == worst[u]], reduce="amin")
    pick = pick.scatter_reduce(0, v[s == worst[v]], order[s == worst[v]], reduce="amin")
    has = pick < edges.numel()
    k = edges[pick.clamp(max=edges.numel() - 1)]
    is_first = (c.batch[k] * n + c.first[k]) == torch.arange(nodes, device=dev)
    sign = torch.where(is_first, torch.sign(c.switch_first[k]), torch.sign(c.switch_second[k]))
    return torch.where(has, sign, 0.0), has


def solve_conflicts(
    rows: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    car_mask: torch.Tensor,
    nominal: torch.Tensor,
    bounds: torch.Tensor,
    penalty: float,
) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """One QP over the cars ``car_mask`` (``(B * N,)`` bool, their variables) with conditions
    ``rows = (u, v, (c_u, c_v), rhs)`` (flat car nodes, ``v = -1`` for none; ``c . w >= rhs``):
    ``(w, slack, solved)`` with ``w`` ``(B * N,)`` (nominal off the mask) and ``slack`` per row."""
    u, v, coef, rhs = rows
    var = torch.cumsum(car_mask.long(), 0) - 1
    cols = torch.stack([var[u], torch.where(v >= 0, var[v.clamp(min=0)], -1)], -1)
    cols = torch.where(torch.stack([car_mask[u], (v >= 0) & car_mask[v.clamp(min=0)]], -1), cols, -1)
    qp = ConflictQP(
        nominal[car_mask].double().cpu().numpy(),
        bounds[car_mask].double().cpu().numpy(),
        cols.cpu().numpy(),
        coef.double().cpu().numpy(),
        rhs.double().cpu().numpy(),
        penalty,
    )
    out = solve(qp)
    w = nominal.clone()
    w[car_mask] = torch.as_tensor(out.w, dtype=w.dtype, device=w.device)
    return w, torch.as_tensor(out.slack, dtype=rhs.dtype, device=rhs.device), out.solved


def qp_conflicts(
    c: PairRows | PairCandidates,
    edges: torch.Tensor,
    labels: torch.Tensor,
    conditions: tuple[torch.Tensor, torch.Tensor],
    inputs: torch.Tensor,
    cars: tuple[torch.Tensor, torch.Tensor],
    rule: FleetFilterSettings,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Decide every conflict of the pairs ``edges`` (indices into ``c``; ``labels`` their groups) in
    one QP: ``conditions = (coef (E, 2), rhs (E,))`` read ``coef . (w_first, w_second) >= rhs``;
    ``inputs`` ``(B, N)`` the inputs so far (returned with these conflicts' cars decided),
    ``cars = (turn bounds, controlled)`` per car node, ``rule`` the penalty and slack tolerance. A
    conflict with a positive slack (or all, if the solver fails) is infeasible: its pairs are
    returned, for the caller's fallback rule to decide its cars (:func:`with_signs`).
    Returns ``(inputs, solved (B,), infeasible (B,), infeasible conflicts' pairs)``."""
    wmax, control = cars
    batch, n = inputs.shape
    dev = inputs.device
    roots = torch.unique(labels)
    solved = torch.zeros(batch, dtype=torch.long, device=dev).scatter_add(0, roots // n, torch.ones_like(roots))
    if edges.numel() == 0:
        return inputs, solved, torch.zeros_like(solved), edges
    inputs = inputs.reshape(-1)
    coef, rhs = conditions
    u = c.batch[edges] * n + c.first[edges]
    v = c.batch[edges] * n + c.second[edges]
    mask = torch.zeros(batch * n, dtype=torch.bool, device=dev)
    mask[u] = True
    mask[v] = True
    mask &= control
    w, slack, ok = solve_conflicts((u, torch.where(control[v], v, -1), coef, rhs), mask, inputs, wmax, rule.penalty)
    bad = torch.zeros(batch * n, dtype=torch.bool, device=dev)
    bad[labels[slack > rule.slack_tolerance] if ok else roots] = True
    out = torch.where(mask, w, inputs)
    return out.reshape(batch, n), solved, bad.reshape(batch, n).sum(1), edges[bad[labels]]


def with_signs(
    inputs: torch.Tensor, signs: tuple[torch.Tensor, torch.Tensor], cars: tuple[torch.Tensor, torch.Tensor]
) -> torch.Tensor:
    """``inputs`` ``(B, N)`` with each car a rule decided (``signs = (sign, decided)``, ``(B * N,)``
    each, e.g. :func:`fallback_inputs`) at that sign of its turn bound, where the filter controls it
    (``cars = (turn bounds, controlled)`` per car node)."""
    sign, has = signs
    wmax, control = cars
    return torch.where((has & control).reshape(inputs.shape), (wmax * sign).reshape(inputs.shape), inputs)


class FleetFilter:
    """The fleet filter (module docstring): ``filter(x, t, u_nominal, present=None) -> (u, FleetInfo)``.

    Args:
        fleet_value: the fleet's pairwise value (:class:`~safety.fleet.value.FleetValue`).
        settings: :class:`FleetFilterSettings` (``dt`` at least).
    """

    def __init__(self, fleet_value: FleetValue, settings: FleetFilterSettings) -> None:
        self.threshold = pair_thresholds(fleet_value, settings)  # checks both arguments' types first
        self.fleet_value = fleet_value
        self.settings = settings
        speed_sum = fleet_value.speed_sum
        self.band = settings.dt * speed_sum if settings.band is None else torch.full_like(speed_sum, settings.band)
        self.level = self.threshold + self.band

    def __call__(
        self, x: torch.Tensor, t: float, u_nominal: torch.Tensor, present: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, FleetInfo]:
        fv = self.fleet_value
        n = fv.num_cars
        x, present, given = checked_inputs(fv, x, u_nominal, present)
        batch = x.shape[0]
        c = fv.candidates(x, t, present, self.level)
        dev, dt = x.device, x.dtype
        theta = self.threshold.to(dev, dt)[c.first, c.second]
        active = c.value <= theta + self.band.to(dev, dt)[c.first, c.second]
        threatened = c.value <= theta
        idx = torch.nonzero(active).squeeze(-1)
        g = conflicts(batch, n, (c.batch[idx], c.first[idx], c.second[idx]), threatened[idx])
        applied, solved, infeasible = self._decide(c, idx, g, given.to(dt), theta, t)
        # a disturbance car's turn rate is not the filter's to choose: it keeps its nominal input
        intervened = g.car_in_conflict & fv.control.to(dev)
        u = torch.where(intervened, applied.to(given.dtype), given)
        min_value = c.cull_bound.clone().scatter_reduce(0, c.batch, c.value, reduce="amin")
        info = FleetInfo(intervened, g.count, solved, infeasible, c.count, min_value, given, u)
        return u, info

    def _decide(
        self,
        c: PairCandidates,
        idx: torch.Tensor,
        g: Conflicts,
        nominal: torch.Tensor,
        theta: torch.Tensor,
        t: float,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(applied (B, N), solved (B,), infeasible (B,))`` for the cars in conflicts."""
        fv = self.fleet_value
        batch, n = nominal.shape
        dev, dt = nominal.device, nominal.dtype
        wmax = fv.turn_bounds.to(dev, dt).repeat(batch)
        control = fv.control.to(dev).repeat(batch)

        def rule(edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            """The policy's signs for the conflicts of ``edges``: the worst pair's ``u*``, replaced by
            the joint greedy input where the policy is greedy and the conflict small enough."""
            sign, has = fallback_inputs(c, edges, c.value, n, batch)
            if self.settings.policy == "greedy":
                when = (t, self.settings.hold)
                ties = self.settings.tie_break
                joint, decided = joint_greedy(fv, c, edges, when, torch.where(has, sign, 0.0), ties)
                sign, has = torch.where(decided, joint, sign), has | decided
            return sign, has

        # conflicts of several pairs: one QP for the whole batch; those it cannot meet wait for the
        # policy's input beside the lone pairs, so the policy runs once per decision
        group = g.in_conflict & (g.edges_in_group > 1)
        qp_edges = idx[group]
        step = self.settings.dt
        coef = torch.stack([step * c.switch_first[qp_edges], step * c.switch_second[qp_edges]], -1)
        rhs = self.settings.gamma * (theta[qp_edges] - c.value[qp_edges]) - step * c.drift[qp_edges]
        out, solved, infeasible, fallen = qp_conflicts(
            c, qp_edges, g.edge_label[group], (coef, rhs), nominal, (wmax, control), self.settings
        )
        # lone pairs (the switch rule: both cars on the policy's input for the pair) and the
        # infeasible conflicts (the fallback): the policy's input, in one call; their cars are
        # in other groups than the QP's feasible conflicts, whose inputs stand
        lone = idx[g.in_conflict & (g.edges_in_group == 1)]
        return with_signs(out, rule(torch.cat([lone, fallen])), (wmax, control)), solved, infeasible
