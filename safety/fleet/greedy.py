"""The joint greedy input of a conflict: the held turn rates that leave its least pair value highest.

Why: at a kink of a pair's value two manoeuvres tie (two cars head-on can both turn left or both
turn right), and the bang-bang ``u*`` of the interpolated gradient can pick neither: each car turns
by the sign of its own partial derivative, and in a head-on pair one car turns left while the other
turns right, so both drift to the same side and stay in line. The switch filter's greedy policy
(:class:`~safety.value_policies.GreedyPolicy`) commits to one manoeuvre by trying held inputs; this is
the same step for a group of cars, scored on every active pair of the group at once.

For a conflict of ``k <= MAX_JOINT_CARS`` cars, each candidate gives every car a turn rate of
``0`` (all cars, the box's centre) or ``+-w_max`` (the box's corners, ``2^k`` of them), held for
``hold`` seconds (:data:`HOLD` by default). Each active pair's relative state is advanced by its pair
problem's own stepper (:func:`~reach.integrators.make_stepper`, RK4 substeps of at most
:data:`SUBSTEP`), and scored as ``min(V(y), min over the substeps of l(y))``; where the pair's second car
is a disturbance, against both of its extreme turn rates. The candidate whose least score over the
group's pairs is highest is applied (ties: the first, the centre). A larger conflict starts from
the best of a few structured candidates: all straight, all turning left, all turning right (cars of
equal speed and turn rate then circle in place, each on its own turning circle, a holding pattern),
and each car on its worst pair's ``u*``. It then descends: each round its worst pair's two cars try
the nine combinations of their signs, and the best is kept if it raises the least score (only
those two cars can raise it alone), for at most :data:`DESCENT_ROUNDS` rounds. The structured
candidates nearly tie where cars converge head-on, as turning changes a head-on distance only at
second order over one step; the descent found the inputs that kept the 8-car circle swaps apart in
1,000 episodes where the structured ones let 4 collide (docs/results/fleets.md). Batched: every
conflict of the batch, every candidate and every pair in one evaluation per pair problem.
"""

from __future__ import annotations

import itertools
import math

import torch

from reach.integrators import make_stepper
from reach.systems.arrays import TORCH
from safety.fleet.graph import components
from safety.fleet.value import FleetValue, PairCandidates

__all__ = ["MAX_JOINT_CARS", "TIE_BREAKS", "joint_greedy", "leximin_best"]

#: how the joint greedy breaks ties between candidates of equal least score (FleetFilterSettings.tie_break)
TIE_BREAKS = ("centre", "leximin")

#: pair scores past the least that a leximin tie-break compares (the least, then up to this many more)
LEXIMIN_LEVELS = 3

#: the largest conflict (cars) the joint greedy decides: ``2^k + 1`` candidates each
MAX_JOINT_CARS = 6

#: the most rounds of the worst-pair descent a conflict of more than MAX_JOINT_CARS cars takes
DESCENT_ROUNDS = 16

#: how long (s) each candidate is held before its pairs' values are read (FleetFilterSettings.hold's
#: default): longer than the switch filter's greedy step (:data:`~safety.value_policies.GREEDY_STEP`,
#: 0.05 s), as over one short step turning changes a head-on distance only at second order, and the
#: candidates of converging cars nearly tie (measured: docs/results/fleets.md)
HOLD = 0.2

#: the held step's RK4 substep (s): the failure margin is checked at each substep's end
SUBSTEP = 0.05

#: each pair's two groups, its cars' ranks in them and their turn bounds
Ends = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def _candidates(k: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(2^k + 1, k)`` turn-rate signs: the centre first, then every corner."""
    corners = list(itertools.product((-1.0, 1.0), repeat=k))
    return torch.tensor([[0.0] * k, *corners], dtype=dtype, device=device)


def _sign_table(
    fv: FleetValue, c: PairCandidates, edges: torch.Tensor, turn: Ends, when: tuple[float, float]
) -> torch.Tensor:
    """``(E, 3, 3)`` the score of each pair ``edges`` when its first car holds ``s_u w_max`` and its
    second ``s_v w_max`` for ``hold`` seconds, at ``[e, s_u + 1, s_v + 1]`` for signs ``s`` in
    ``{-1, 0, 1}``, with ``when = (t, hold)`` and ``turn`` the pairs' ends (their turn bounds last);
    a disturbance second car is taken at its worse extreme whatever ``s_v``.

    Every candidate of the policy gives each car one of these three signs, so a candidate's pair
    scores are entries of this table: each pair is stepped once per sign pair, not once per
    candidate and descent round. The rows are the same arithmetic on the same inputs as stepping
    each candidate, elementwise, so the scores are too."""
    t, hold = when
    wu, wv = turn[4], turn[5]
    signs = torch.tensor((-1.0, 0.0, 1.0), dtype=wu.dtype, device=wu.device)
    w = torch.stack(
        [(signs[:, None, None] * wu).expand(3, 3, -1), (signs[None, :, None] * wv).expand(3, 3, -1)], -1
    ).reshape(9, -1, 2)
    count, e = w.shape[0], edges.numel()
    out = torch.full((count, e), math.inf, dtype=w.dtype, device=w.device)
    kinds = fv.pair_kind[c.first[edges], c.second[edges]].to(w.device)
    for kind, sol in enumerate(fv.solutions):
        mine = torch.nonzero(kinds == kind).squeeze(-1)
        if mine.numel() == 0:
            continue
        ps = sol.system
        substeps = max(1, math.ceil(hold / SUBSTEP - 1e-9))
        advance = make_stepper(ps, hold / substeps, "rk4", TORCH)
        rel = c.rel[edges[mine]].to(w.dtype).unsqueeze(0).expand(count, -1, -1).reshape(-1, 3)
        held = w[:, mine].reshape(-1, 2)
        if ps.disturbance_dim:  # the second car attacks: both extremes, the worse one counts
            wd = ps.disturbance_bounds.high[0]
            options = [(held[:, :1], torch.full_like(held[:, :1], s * wd)) for s in (-1.0, 1.0)]
        else:
            options = [(held, held[:, :0])]
        scores = []
        for u, d in options:
            uc = ps.input_columns(u, ps.control_bounds, "u")
            dc = ps.input_columns(d, ps.disturbance_bounds, "d")
            low = ps.failure_margin(rel)
            cols = TORCH.unbind(rel)
            for _ in range(substeps):
                cols = advance(cols, uc, dc)
                low = torch.minimum(low, ps.failure_margin_columns(cols, TORCH))
            y = TORCH.stack(cols, like=low)
            value = sol.value(y, t).to(low.dtype)
            if not bool(torch.isfinite(value).all() & torch.isfinite(low).all()):
                raise ValueError(f"the fleet's joint greedy step met a non-finite pair value (t = {t})")
            scores.append(torch.minimum(value, low))
        out[:, mine] = torch.stack(scores).amin(0).reshape(count, -1)
    return out.T.reshape(e, 3, 3)


def joint_greedy(
    fv: FleetValue,
    c: PairCandidates,
    edges: torch.Tensor,
    when: tuple[float, float],
    gradient_sign: torch.Tensor,
    ties: str = "centre",
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sign (B * N,), decided (B * N,) bool)``: the turn-rate sign each car of the conflicts
    formed by the pairs ``edges`` (indices into ``c``; each conflict given whole) takes (module
    docstring), at time-to-go and hold ``when = (t, hold)``; ``gradient_sign`` ``(B * N,)`` is each
    car's worst-pair ``u*`` sign, the candidate a conflict of more than :data:`MAX_JOINT_CARS` cars
    weighs beside all-straight, all-left and all-right. ``decided`` marks the cars of the conflicts.
    ``ties`` (:data:`TIE_BREAKS`): among candidates whose least pair score ties, ``"centre"`` takes
    the first (the centre, all straight), ``"leximin"`` the one whose next least score is highest,
    and so on (:func:`leximin_best`)."""
    if ties not in TIE_BREAKS:
        raise ValueError(f"ties must be one of {TIE_BREAKS}, got {ties!r}")
    n = fv.num_cars
    nodes = gradient_sign.numel()
    dev, dtype = c.value.device, c.value.dtype
    sign = torch.zeros(nodes, dtype=dtype, device=dev)
    decided = torch.zeros(nodes, dtype=torch.bool, device=dev)
    if edges.numel() == 0:
        return sign, decided
    u = c.batch[edges] * n + c.first[edges]
    v = c.batch[edges] * n + c.second[edges]
    label = components(nodes, u, v)
    cars = torch.unique(torch.cat([u, v]))
    # each car's rank in its group (groups in label order, cars in node order)
    cars = cars[torch.argsort(label[cars] * nodes + cars)]
    group, compact = torch.unique(label[cars], return_inverse=True)
    position = torch.arange(cars.numel(), device=dev)
    start = torch.full((group.numel(),), cars.numel(), dtype=torch.long, device=dev)
    start = start.scatter_reduce(0, compact, position, reduce="amin")
    size = torch.zeros(group.numel(), dtype=torch.long, device=dev).scatter_add(0, compact, torch.ones_like(compact))
    rank = torch.full((nodes,), -1, dtype=torch.long, device=dev)
    rank[cars] = position - start[compact]
    group_of = torch.full((nodes,), -1, dtype=torch.long, device=dev)
    group_of[cars] = compact
    k = int(size.max())
    small = size <= MAX_JOINT_CARS
    k_small = int(size[small].max()) if bool(small.any()) else 0
    full = _candidates(k_small, dtype, dev)  # (2^k_small + 1, k_small)
    count = max(full.shape[0], 4)
    cand = torch.zeros(group.numel(), count, k, dtype=dtype, device=dev)  # rows past a group's own: straight
    cand[small.nonzero().squeeze(-1)[:, None], : full.shape[0], :k_small] = full
    large = (~small).nonzero().squeeze(-1)
    if large.numel():
        cand[large, 1] = 1.0
        cand[large, 2] = -1.0
        big = cars[~small[compact]]
        cand[group_of[big], 3, rank[big]] = gradient_sign[big].to(dtype)
    wmax = fv.turn_bounds.to(dev, dtype)
    gu, gv = group_of[u], group_of[v]
    ends = (gu, gv, rank[u], rank[v], wmax[c.first[edges]], wmax[c.second[edges]])
    table = _sign_table(fv, c, edges, ends, when)  # (E, 3, 3)
    scores = _candidate_scores(table, cand, ends)  # (C, E)
    least = torch.full((count, group.numel()), math.inf, dtype=dtype, device=dev)
    least = least.scatter_reduce(1, gu.expand(count, -1), scores, reduce="amin")
    # (G,): ties go to the first, the centre, or to the candidate whose next least scores are highest
    best = least.argmax(0) if ties == "centre" else leximin_best(scores, gu, least)
    chosen = cand[torch.arange(group.numel(), device=dev), best]  # (G, k)
    if large.numel():
        chosen = _descend(table, chosen, ends, large)
    sign[cars] = chosen[compact, rank[cars]]
    decided[cars] = True
    return sign, decided


def _candidate_scores(table: torch.Tensor, cand: torch.Tensor, ends: Ends) -> torch.Tensor:
    """``(C, E)`` each pair's score under each of its group's ``C`` candidates ``cand`` ``(G, C, k)``
    (signs in ``{-1, 0, 1}``), read from the pairs' sign table ``(E, 3, 3)`` (:func:`_sign_table`);
    ``ends`` = each pair's two groups, ranks in them and turn bounds."""
    gu, gv, ru, rv, _, _ = ends
    su = cand[gu, :, ru].T.long() + 1
    sv = cand[gv, :, rv].T.long() + 1
    return table[torch.arange(table.shape[0], device=table.device), su, sv]


def _descend(table: torch.Tensor, chosen: torch.Tensor, ends: Ends, large: torch.Tensor) -> torch.Tensor:
    """``chosen`` ``(G, k)`` improved for the ``large`` groups by a worst-pair descent: each round,
    every such group tries the 9 sign combinations of the two cars of its worst pair (the only cars
    whose inputs can raise the least score alone) and keeps the best if it raises the group's least
    score; at most :data:`DESCENT_ROUNDS` rounds, stopping early when no group improves. A round
    scores only the pairs of those two cars: the others' scores stand. Scores are read from the
    pairs' sign table ``(E, 3, 3)`` (:func:`_sign_table`)."""
    dev, dtype = chosen.device, chosen.dtype
    mine = torch.isin(ends[0], large)
    table = table[mine]
    ends = tuple(e[mine] for e in ends)
    gu, _, ru, rv, _, _ = ends
    groups = chosen.shape[0]
    # the sign combinations the worst pair's two cars try; the group's current choice goes first
    combos = torch.tensor(list(itertools.product((-1.0, 0.0, 1.0), repeat=2)), dtype=dtype, device=dev)
    tries = combos.shape[0] + 1
    rows = torch.arange(groups, device=dev)
    now = _candidate_scores(table, chosen[:, None, :], ends)[0]  # (E,) the pairs' scores now
    order = torch.arange(now.numel(), device=dev)
    for _ in range(DESCENT_ROUNDS):
        least = torch.full((groups,), math.inf, dtype=dtype, device=dev).scatter_reduce(0, gu, now, reduce="amin")
        low = now == least[gu]
        worst = torch.full((groups,), now.numel(), dtype=torch.long, device=dev)
        worst = worst.scatter_reduce(0, gu[low], order[low], reduce="amin")
        has = worst < now.numel()
        e = worst.clamp(max=now.numel() - 1)
        a, b = ru[e], rv[e]  # each group's worst pair's two cars (ranks in the group)
        cand = chosen[:, None, :].repeat(1, tries, 1)  # (G, 10, k)
        cand[rows[:, None], torch.arange(1, tries, device=dev), a[:, None]] = combos[:, 0]
        cand[rows[:, None], torch.arange(1, tries, device=dev), b[:, None]] = combos[:, 1]
        # only the pairs of those two cars change score: score them, keep the others' scores
        touch = has[gu] & ((ru == a[gu]) | (ru == b[gu]) | (rv == a[gu]) | (rv == b[gu]))
        kept = torch.full((groups,), math.inf, dtype=dtype, device=dev)
        kept = kept.scatter_reduce(0, gu[~touch], now[~touch], reduce="amin")
        near = tuple(x[touch] for x in ends)
        scores = _candidate_scores(table[touch], cand, near)  # (10, T)
        tried = torch.full((tries, groups), math.inf, dtype=dtype, device=dev)
        tried = tried.scatter_reduce(1, gu[touch].expand(tries, -1), scores, reduce="amin")
        tried = torch.minimum(tried, kept)
        best = tried.argmax(0)
        better = has & (tried[best, rows] > least)  # has: only the large groups have pairs here
        if not bool(better.any()):
            break
        chosen = torch.where(better[:, None], cand[rows, best], chosen)
        gt = gu[touch]
        now[touch] = torch.where(better[gt], scores[best[gt], torch.arange(gt.numel(), device=dev)], now[touch])
    return chosen


def leximin_best(scores: torch.Tensor, group: torch.Tensor, least: torch.Tensor) -> torch.Tensor:
    """``(G,)`` each group's candidate by leximin: the highest least pair score ``least`` ``(C, G)``;
    among exact ties, the highest next least, and so on for :data:`LEXIMIN_LEVELS` more scores; then
    the first. ``scores`` ``(C, E)`` are the candidates' pair scores, ``group`` ``(E,)`` each pair's group.

    Why: a pair whose cars' inputs do not touch the group's least pair scores the same under every
    sign of those cars, so the least ties across them, and the first candidate (all straight) wins
    where one of those signs would hold the pair apart. Seen in the fleet study's collisions
    (docs/results/fleet_collisions.md): a pair held straight while its value fell, inside a conflict
    whose least pair was another."""
    count, groups = least.shape
    edges = scores.shape[1]
    index = group.expand(count, -1)
    order = torch.arange(edges, device=scores.device).expand(count, -1)
    alive = torch.ones(count, groups, dtype=torch.bool, device=scores.device)
    rest, level = scores, least
    for _ in range(LEXIMIN_LEVELS + 1):
        top = torch.where(alive, level, -math.inf).amax(0)
        alive = alive & (level == top)
        if not bool((alive.sum(0) > 1).any()):
            break
        # set aside each candidate's least pair (the first that reaches it) and read the next least
        at = rest == level.gather(1, index)
        first = torch.full((count, groups), edges, dtype=torch.long, device=scores.device)
        first = first.scatter_reduce(1, index, torch.where(at, order, edges), reduce="amin")
        drop = torch.zeros_like(at).scatter_(1, first.clamp(max=edges - 1), True) & (first < edges).gather(1, index)
        rest = torch.where(drop, math.inf, rest)
        level = torch.full_like(least, math.inf).scatter_reduce(1, index, rest, reduce="amin")
    return alive.to(torch.long).argmax(0)
