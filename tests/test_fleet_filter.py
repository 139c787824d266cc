"""The fleet filter (safety.fleet): pairwise values for N cars, the conflict rule, the QP, the baselines."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from groundtruth.pairwise import PairwiseUnion, relative_state
from groundtruth.solution import GridSolution
from reach.systems import MultiVehicle, RelativePair
from reach.systems.multivehicle import Car
from safety.filters.base import SafetyFilter
from safety.fleet import (
    CBFSettings,
    DistanceCBF,
    FleetFilter,
    FleetFilterSettings,
    FleetValue,
    NaiveUnionSwitch,
)
from safety.fleet.graph import components
from safety.fleet.qp import ConflictQP, solve

PAIR = "training/pretrained/relativepair.npz"
F64 = torch.float64


@pytest.fixture(scope="module")
def pair() -> GridSolution:
    return GridSolution.load(PAIR, outside="clamp")


def fleet(n: int, half_width: float = 1.0, speed: float = 0.6, turn: float = 1.1) -> MultiVehicle:
    return MultiVehicle([Car(speed, turn)] * n, half_width=half_width)


def states(n: int, batch: int, spread: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    pos = (torch.rand(batch, 2 * n, generator=g, dtype=F64) * 2 - 1) * spread
    th = (torch.rand(batch, n, generator=g, dtype=F64) * 2 - 1) * math.pi
    return torch.cat([pos, th], 1)


def nominal(n: int, batch: int, seed: int, scale: float = 1.5) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed + 1000)
    return (torch.rand(batch, n, generator=g, dtype=F64) * 2 - 1) * scale


class Smooth:
    """A smooth value function of a RelativePair (not a safe set, a test of the calculus)."""

    time_range = (0.0, 1.0)
    times = torch.tensor([0.0, 1.0], dtype=torch.float64)

    def __init__(self, system: RelativePair, tilt: float = 0.1) -> None:
        self.system = system
        self.tilt = tilt

    def value(self, x: torch.Tensor, t: float) -> torch.Tensor:
        r0, r1, r2 = x.unbind(-1)
        return torch.hypot(r0, r1) - 0.55 + self.tilt * torch.sin(r2) + 0.05 * r0 * r1

    def gradient(self, x: torch.Tensor, t: float) -> torch.Tensor:
        with torch.enable_grad():
            y = x.detach().requires_grad_(True)
            return torch.autograd.grad(self.value(y, t).sum(), y)[0]

    def value_and_gradient(self, x: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor]:
        return self.value(x, t), self.gradient(x, t)


# ---------------------------------------------------------------------------------------- N = 2
@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10_000), t=st.sampled_from([1.0, 0.55]), dt=st.sampled_from([0.05, 0.1]))
def test_at_two_cars_the_fleet_filter_is_the_switch_filter_to_the_bit(pair, seed, t, dt):
    system = fleet(2)
    ff = FleetFilter(FleetValue(system, pair), FleetFilterSettings(dt=dt, threshold=2 * 1.2 * dt, policy="gradient"))
    theta = float(ff.threshold[0, 1])
    sf = SafetyFilter(PairwiseUnion(system, pair), threshold=theta, policy="gradient")
    x, u_nom = states(2, 4000, 0.7, seed), nominal(2, 4000, seed)
    u, info = ff(x, t, u_nom)
    u_ref, ref = sf(x, t, u_nom)
    assert torch.equal(u, u_ref)
    assert torch.equal(info.intervened.any(1), ref.intervened)
    assert 0.05 < float(ref.intervened.double().mean()) < 0.95  # both branches were exercised
    assert torch.equal(info.nominal, ref.nominal)  # out-of-bound nominal inputs clipped alike


@pytest.mark.parametrize("n", [3, 4])
def test_the_naive_union_switch_is_the_switch_filter_on_the_pairwise_union(pair, n):
    system = fleet(n)
    naive = NaiveUnionSwitch(FleetValue(system, pair), FleetFilterSettings(dt=0.05, threshold=2 * 1.2 * 0.05))
    sf = SafetyFilter(PairwiseUnion(system, pair), threshold=float(naive.threshold[0, 1]), policy="gradient")
    x, u_nom = states(n, 5000, 0.9, n), nominal(n, 5000, n)
    u, info = naive(x, 1.0, u_nom)
    u_ref, ref = sf(x, 1.0, u_nom)
    assert torch.equal(u, u_ref)
    assert torch.equal(info.intervened.any(1), ref.intervened)
    assert 0.05 < float(ref.intervened.double().mean()) < 0.95


# ---------------------------------------------------------------------------------------- pairs
def euler(x: torch.Tensor, w: torch.Tensor, speeds: torch.Tensor, h: float) -> torch.Tensor:
    n = w.shape[1]
    pos, th = x[:, : 2 * n].reshape(-1, n, 2), x[:, 2 * n :]
    vel = speeds[None, :, None] * torch.stack([torch.cos(th), torch.sin(th)], -1)
    return torch.cat([(pos + h * vel).reshape(-1, 2 * n), th + h * w], 1)


def test_the_linearised_step_has_the_sign_and_size_of_a_finite_difference():
    cars = [Car(0.6, 1.1), Car(0.5, 0.9), Car(0.6, 1.1, "disturbance")]
    system = MultiVehicle(cars, half_width=1.0)
    kinds = {(0.6, 0.5, 1.1, 0.9, "control"), (0.6, 0.6, 1.1, 1.1, "disturbance"), (0.5, 0.6, 0.9, 1.1, "disturbance")}
    vfs = [Smooth(RelativePair(v1, v2, w1, w2, role)) for v1, v2, w1, w2, role in kinds]
    fv = FleetValue(system, vfs)
    x = states(3, 3000, 0.55, 7)  # relative positions inside the pair box (beyond it a value is clamped)
    c = fv.candidates(x, 1.0, level=10.0)
    assert c.count == 3 * 3000  # every pair within reach at this level
    w = nominal(3, 3000, 7, 1.0) * fv.turn_bounds
    # the disturbance car turns the worst way for each pair: test one pair kind at a time
    for second_is_car_2 in (False, True):
        rows = (c.second == 2) if second_is_car_2 else (c.second != 2)
        b, f, s = c.batch[rows], c.first[rows], c.second[rows]
        wk = w[b].clone()
        if second_is_car_2:
            wk[torch.arange(b.numel()), s] = -fv.turn_bounds[2] * torch.sign(c.gradient[rows, 2])
        h = 1e-6
        x1 = euler(x[b], wk, fv.speeds, h)
        n = 3
        idx = torch.arange(b.numel())
        p1 = x1[:, : 2 * n].reshape(-1, n, 2)
        rel = relative_state(p1[idx, f], p1[idx, s], x1[idx, 2 * n + f], x1[idx, 2 * n + s])
        fd = torch.empty(b.numel(), dtype=F64)
        for k, vf in enumerate(vfs):  # the kinds of these pairs
            m = fv.pair_kind[f, s] == k
            fd[m] = (vf.value(rel[m], 1.0) - c.value[rows][m]) / h
        predicted = c.drift[rows] + c.switch_first[rows] * wk[idx, f] + c.switch_second[rows] * wk[idx, s]
        err = (fd - predicted).abs()
        assert float(err.max()) < 1e-4, (second_is_car_2, float(err.max()), int(err.argmax()))


def test_the_pair_grid_steps_as_its_linearisation_says(pair):
    """On the shipped grid: over a short step, the value moves as predicted, to the grid's resolution."""
    fv = FleetValue(fleet(4, 1.0), pair)
    x = states(4, 2000, 0.8, 3)
    c = fv.candidates(x, 1.0, level=0.5)
    w = nominal(4, 2000, 3, 1.0) * 1.1
    b, f, s = c.batch, c.first, c.second
    h = 0.01
    x1 = euler(x[b], w[b], fv.speeds, h)
    v1 = fv.pair_values(x1, 1.0, level=5.0)[torch.arange(b.numel()), f, s]
    fd = (v1 - c.value) / h
    predicted = c.drift + c.switch_first * w[b, f] + c.switch_second * w[b, s]
    inside = (c.rel[:, :2].abs() < 1.5).all(-1)
    err = (fd - predicted)[inside].abs()
    assert float(err.median()) < 0.05
    # the sign of the turn-rate terms: a step with the car's turn flipped moves V the predicted way
    strong = inside & (c.switch_first.abs() > 0.3)
    w2 = w.clone()
    w2[b[strong], f[strong]] = -w[b[strong], f[strong]]
    x2 = euler(x[b], w2[b], fv.speeds, h)
    v2 = fv.pair_values(x2, 1.0, level=5.0)[torch.arange(b.numel()), f, s]
    change = (v1 - v2)[strong]
    expected = (c.switch_first * 2 * w[b, f] * h)[strong]
    agree = torch.sign(change) == torch.sign(expected)
    assert float(agree.double().mean()) > 0.95


def test_heterogeneous_cars_use_each_pair_kind_and_the_swapped_one():
    cars = [Car(0.6, 1.1), Car(0.4, 0.8), Car(0.6, 1.1), Car(0.4, 0.8)]
    system = MultiVehicle(cars, half_width=1.0)
    fast, slow = RelativePair(0.6, 0.6, 1.1, 1.1), RelativePair(0.4, 0.4, 0.8, 0.8)
    mixed, mixed_back = RelativePair(0.6, 0.4, 1.1, 0.8), RelativePair(0.4, 0.6, 0.8, 1.1)
    vfs = {
        fast: Smooth(fast, 0.1),
        slow: Smooth(slow, 0.2),
        mixed: Smooth(mixed, 0.3),
        mixed_back: Smooth(mixed_back, 0.4),
    }
    x = states(4, 500, 0.5, 11)
    ours = FleetValue(system, vfs).pair_values(x, 1.0, level=10.0)
    union = PairwiseUnion(system, vfs)
    theirs = union.pair_values(x, 1.0)
    for k, (i, j) in enumerate(union.pairs):
        assert torch.equal(ours[:, i, j], theirs[:, k]), (i, j)
    # without the slow-first problem, the (slow, fast) pairs swap roles and the fast car is the frame
    swapped = FleetValue(system, [vfs[fast], vfs[slow], vfs[mixed]])
    c = swapped.candidates(x, 1.0, level=10.0)
    assert c.count == 6 * 500
    assert bool((swapped.speeds[c.first] >= swapped.speeds[c.second]).all())
    cross = swapped.speeds[c.first] != swapped.speeds[c.second]
    assert torch.equal(c.value[cross], vfs[mixed].value(c.rel[cross], 1.0))
    with pytest.raises(ValueError, match="no pair solution"):
        FleetValue(system, [vfs[fast], vfs[slow]])


# ---------------------------------------------------------------------------------------- the cull
def test_a_culled_pair_never_matters_within_the_horizon(pair):
    # the bound behind the cull, on the shipped grid: V(r, t) >= |r| - R - (v1 + v2) t inside its box
    g = torch.Generator().manual_seed(0)
    r = (torch.rand(200_000, 3, generator=g, dtype=F64) * 2 - 1) * torch.tensor([1.6, 1.6, math.pi], dtype=F64)
    for t in (1.0, 0.5, 0.1):
        assert bool((pair.value(r, t) >= r[:, :2].norm(dim=-1) - 0.25 - 1.2 * t - 1e-9).all())
    # so a culled pair's value exceeds the activation level, at random fleet states
    n = 8
    system = fleet(n, 3.0)
    fv = FleetValue(system, pair)
    # a low level (the one-step threshold), so that many culled pairs still lie in the grid's box
    # where their value can be read: the default level culls beyond most of the box
    ff = FleetFilter(fv, FleetFilterSettings(dt=0.05, threshold=0.12))
    x = states(n, 2000, 1.8, 1)
    everything = PairwiseUnion(system, pair).pair_values(x, 1.0)
    pairs = PairwiseUnion(system, pair).pairs
    i, j = torch.tensor([p[0] for p in pairs]), torch.tensor([p[1] for p in pairs])
    pos = x[:, : 2 * n].reshape(-1, n, 2)
    dist = (pos[:, i] - pos[:, j]).norm(dim=-1)
    culled = dist >= fv.cull_distance(1.0, ff.level)[i, j]
    rel = PairwiseUnion(system, pair).relative_states(x)
    in_box = (rel[..., :2].abs() <= 1.6).all(-1)
    assert int((culled & in_box).sum()) > 1000
    assert bool((everything[culled & in_box] > ff.level[i, j].expand_as(dist)[culled & in_box]).all())

    # and the filter decides alike with no cull at all
    class NoCull(FleetValue):
        def cull_distance(self, t, level=0.0):
            return torch.full_like(self.speed_sum, math.inf)

    u_nom = nominal(n, 2000, 1)
    u, info = ff(x, 1.0, u_nom)
    u_all, info_all = FleetFilter(NoCull(system, pair), ff.settings)(x, 1.0, u_nom)
    assert torch.equal(u, u_all)
    assert info.pairs < info_all.pairs
    assert int(info.conflicts.sum()) > 0


def test_a_fleet_of_64_evaluates_few_pairs(pair):
    n = 64
    side = torch.arange(8, dtype=F64) * 1.3
    pos = torch.stack(torch.meshgrid(side, side, indexing="ij"), -1).reshape(1, -1)
    x = torch.cat([pos, torch.zeros(1, n, dtype=F64)], 1)
    fv = FleetValue(fleet(n, 10.0), pair)
    ff = FleetFilter(fv, FleetFilterSettings(dt=0.05))
    u, info = ff(x, 1.0, torch.zeros(1, n, dtype=F64))
    dist = torch.cdist(pos.reshape(n, 2), pos.reshape(n, 2))
    near = torch.triu(dist < fv.cull_distance(1.0, ff.level), 1)
    assert info.pairs == int(near.sum()) < 2016 // 8  # each car's 8 neighbours at most, not every pair
    assert torch.equal(u, torch.zeros(1, n, dtype=F64))  # 1.3 m apart, side by side: no conflict


# ---------------------------------------------------------------------------------------- the QP
def pinch() -> torch.Tensor:
    """Car 0 between car 1 (ahead, facing it) and car 2 (behind, chasing): no turn clears both."""
    pos = [0.0, 0.0, 0.42, 0.0, -0.42, 0.02]
    return torch.tensor([[*pos, 0.0, math.pi, 0.0]], dtype=F64)


def test_an_infeasible_conflict_falls_back_to_each_cars_worst_pair_and_is_counted(pair):
    system = fleet(3, 2.0)
    fv = FleetValue(system, pair)
    ff = FleetFilter(fv, FleetFilterSettings(dt=0.05, policy="gradient"))
    x = pinch()
    u, info = ff(x, 1.0, torch.zeros(1, 3, dtype=F64))
    assert int(info.conflicts[0]) == 1 and int(info.solved[0]) == 1
    assert int(info.infeasible[0]) == 1
    c = fv.candidates(x, 1.0, level=ff.level)
    for car in range(3):
        mine = (c.first == car) | (c.second == car)
        k = torch.nonzero(mine).squeeze(-1)[c.value[mine].argmin()]
        s = c.switch_first[k] if int(c.first[k]) == car else c.switch_second[k]
        assert float(u[0, car]) == 1.1 * float(torch.sign(s))
    assert bool(info.intervened.all())


def _rel(x: torch.Tensor, n: int, i: int, j: int) -> torch.Tensor:
    return relative_state(x[:, 2 * i : 2 * i + 2], x[:, 2 * j : 2 * j + 2], x[:, 2 * n + i], x[:, 2 * n + j])


def _held_score(pair: GridSolution, rel: torch.Tensor, w: torch.Tensor, t: float) -> torch.Tensor:
    """min(V, l) of relative states after the greedy hold with turn rates ``w`` held (independent
    of the filter: the pair system's own stepper)."""
    from reach.integrators import make_stepper  # lazy: only these greedy checks step the pair
    from reach.systems.arrays import TORCH  # lazy: as above
    from safety.fleet.greedy import HOLD, SUBSTEP  # lazy: as above

    ps = pair.system
    k = max(1, math.ceil(HOLD / SUBSTEP - 1e-9))
    step = make_stepper(ps, HOLD / k, "rk4", TORCH)
    cols, low = TORCH.unbind(rel), ps.failure_margin(rel)
    uc = ps.input_columns(w, ps.control_bounds, "u")
    dc = ps.input_columns(w[:, :0], ps.disturbance_bounds, "d")
    for _ in range(k):
        cols = step(cols, uc, dc)
        low = torch.minimum(low, ps.failure_margin_columns(cols, TORCH))
    return torch.minimum(pair.value(TORCH.stack(cols, like=low), t), low)


def test_the_greedy_infeasible_conflict_takes_the_held_input_that_leaves_its_least_pair_highest(pair):
    fv = FleetValue(fleet(3, 2.0), pair)
    ff = FleetFilter(fv, FleetFilterSettings(dt=0.05))  # policy "greedy", the default
    x = pinch()
    u, info = ff(x, 1.0, torch.zeros(1, 3, dtype=F64))
    assert int(info.infeasible[0]) == 1 and bool(info.intervened.all())
    pairs = [(0, 1), (0, 2), (1, 2)]

    def least(w: torch.Tensor) -> float:  # the least score over the three pairs under held rates w (3,)
        scores = []
        for i, j in pairs:
            rel = _rel(x, 3, i, j)
            scores.append(float(_held_score(pair, rel, torch.stack([w[i], w[j]])[None], 1.0)[0]))
        return min(scores)

    import itertools  # lazy: only this brute force enumerates the candidates

    options = [torch.zeros(3, dtype=F64)] + [
        torch.tensor(c, dtype=F64) * 1.1 for c in itertools.product((-1, 1), repeat=3)
    ]
    best = max(least(w) for w in options)
    assert least(u[0]) == pytest.approx(best, abs=1e-12)
    assert best > least(torch.zeros(3, dtype=F64)) or torch.equal(u[0], torch.zeros(3, dtype=F64))


def test_at_two_cars_the_greedy_fleet_filter_commits_a_head_on_pair_to_one_manoeuvre(pair):
    # head-on, nearly in line: u* of the kink's blended gradient turns both cars to the same side
    # of the world (they stay in line); the greedy step turns both to their own right or own left
    system = fleet(2, 2.0)
    x = torch.tensor([[0.0, 0.0, 0.9, 0.004, 0.0, math.pi]], dtype=F64)
    u, info = FleetFilter(FleetValue(system, pair), FleetFilterSettings(dt=0.05))(x, 1.0, torch.zeros(1, 2, dtype=F64))
    assert bool(info.intervened.all())
    assert float(u[0, 0]) == float(u[0, 1]) != 0.0  # both own-left or both own-right: they part
    rel = _rel(x, 2, 0, 1)
    assert float(_held_score(pair, rel, u[0][None], 1.0)[0]) > float(
        _held_score(pair, rel, -u[0][None] * torch.tensor([1.0, -1.0], dtype=F64), 1.0)[0]
    )


def converging(n: int, radius: float, seed: int) -> torch.Tensor:
    """``n`` cars on a circle of ``radius``, each heading for the centre, slightly jittered."""
    g = torch.Generator().manual_seed(seed)
    ang = torch.arange(n, dtype=F64) * 2 * math.pi / n + 0.05 * torch.randn(n, generator=g, dtype=F64)
    pos = torch.stack([radius * torch.cos(ang), radius * torch.sin(ang)], -1).reshape(1, -1)
    heading = ang + math.pi + 0.05 * torch.randn(n, generator=g, dtype=F64)
    return torch.cat([pos, heading[None]], 1)


def test_a_conflict_too_large_to_enumerate_descends_from_its_best_structured_input(pair):
    # eight cars converging on one point: one infeasible conflict of all eight (more than
    # MAX_JOINT_CARS), where all-straight, all-left and all-right nearly tie. The descent over the
    # worst pair's two cars starts from the best of those and of each car on its worst pair's u*
    # (the gradient policy's fallback): it is never worse, and here it is strictly better once
    n = 8
    fv = FleetValue(fleet(n, 3.0), pair)
    zero = torch.zeros(1, n, dtype=F64)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    gains = []
    for seed in range(3):
        x = converging(n, 1.0, seed)
        u, info = FleetFilter(fv, FleetFilterSettings(dt=0.05))(x, 1.0, zero)
        assert int(info.conflicts[0]) == 1 and int(info.infeasible[0]) == 1 and bool(info.intervened.all())
        gradient, _ = FleetFilter(fv, FleetFilterSettings(dt=0.05, policy="gradient"))(x, 1.0, zero)

        def least(w: torch.Tensor, x: torch.Tensor = x) -> float:  # least score over every pair, rates w held
            return min(
                float(_held_score(pair, _rel(x, n, i, j), torch.stack([w[i], w[j]])[None], 1.0)[0]) for i, j in pairs
            )

        structured = [torch.full((n,), s * 1.1, dtype=F64) for s in (0.0, 1.0, -1.0)] + [gradient[0]]
        gains.append(least(u[0]) - max(least(w) for w in structured))
    assert min(gains) >= -1e-12 and max(gains) > 1e-3, gains


def test_the_qp_solution_meets_every_condition_of_its_conflict(pair):
    n = 4
    fv = FleetValue(fleet(n, 2.0), pair)
    settings_ = FleetFilterSettings(dt=0.05, gamma=0.2, threshold=2 * 1.2 * 0.05, policy="gradient")
    ff = FleetFilter(fv, settings_)
    x, u_nom = states(n, 20_000, 1.1, 5), nominal(n, 20_000, 5, 1.0)
    u, info = ff(x, 1.0, u_nom)
    ok = (info.solved == 1) & (info.infeasible == 0) & (info.conflicts == 1)
    assert int(ok.sum()) >= 5
    c = fv.candidates(x, 1.0, level=ff.level)
    theta = ff.threshold[c.first, c.second]
    active = c.value <= theta + ff.band[c.first, c.second]
    mine = active & ok[c.batch] & info.intervened[c.batch, c.first] & info.intervened[c.batch, c.second]
    b, f, s = c.batch[mine], c.first[mine], c.second[mine]
    after = c.value[mine] + 0.05 * (c.drift[mine] + c.switch_first[mine] * u[b, f] + c.switch_second[mine] * u[b, s])
    need = theta[mine] + (1 - 0.2) * (c.value[mine] - theta[mine])
    assert float((need - after).max()) < 1e-7
    assert bool((u.abs() <= 1.1).all())


def test_the_stacked_qp_is_the_closest_input_and_flags_the_infeasible_block():
    # block 1 (vars 0, 1): w0 - w1 >= 1; block 2 (var 2): w2 >= 1 and -w2 >= -0.5 (infeasible)
    qp = ConflictQP(
        np.array([0.5, -0.2, 0.0]),
        np.array([1.1, 1.1, 1.1]),
        np.array([[0, 1], [2, -1], [2, -1]]),
        np.array([[1.0, -1.0], [1.0, 0.0], [-1.0, 0.0]]),
        np.array([1.0, 1.0, -0.5]),
    )
    out = solve(qp)
    assert out.solved
    assert np.allclose(out.w[:2], [0.65, -0.35], atol=1e-7)  # the projection onto w0 - w1 = 1
    assert out.slack[0] < 1e-7 and out.slack[1:].sum() > 0.4


def test_label_propagation_finds_the_components():
    src = torch.tensor([0, 2, 3, 6, 8])
    dst = torch.tensor([1, 1, 4, 7, 7])
    assert components(10, src, dst).tolist() == [0, 0, 0, 3, 3, 5, 6, 6, 6, 9]


def test_the_distance_cbf_meets_its_conditions_where_feasible(pair):
    n = 4
    cbf = DistanceCBF(FleetValue(fleet(n, 2.0), pair), CBFSettings(dt=0.05, gamma=0.5))
    x, u_nom = states(n, 2000, 1.2, 9), nominal(n, 2000, 9, 1.0)
    u, info = cbf(x, 1.0, u_nom)
    assert bool((u.abs() <= 1.1 + 1e-12).all())
    assert int(info.conflicts.sum()) > 0 and int(info.solved.sum()) == int(info.conflicts.sum())
    calm = info.conflicts == 0
    assert torch.equal(u[calm], info.nominal[calm])


# ---------------------------------------------------------------------------------------- refusals
def test_bad_input_is_refused_naming_it(pair):
    ff = FleetFilter(FleetValue(fleet(3, 2.0), pair), FleetFilterSettings(dt=0.05))
    x, u_nom = states(3, 4, 0.5, 0), nominal(3, 4, 0, 1.0)
    bad = x.clone()
    bad[1, 2] = math.nan
    with pytest.raises(ValueError, match="states contain NaN or inf"):
        ff(bad, 1.0, u_nom)
    for value in (math.nan, math.inf):
        u_bad = u_nom.clone()
        u_bad[0, 1] = value
        with pytest.raises(ValueError, match="u_nominal contains NaN or inf"):
            ff(x, 1.0, u_bad)
    with pytest.raises(ValueError, match="shape"):
        ff(x[:, :-1], 1.0, u_nom)
    with pytest.raises(ValueError, match="u_nominal must have shape"):
        ff(x, 1.0, u_nom[:, :2])
    with pytest.raises(ValueError, match="present must be a bool"):
        ff(x, 1.0, u_nom, torch.ones(4, 3))
    with pytest.raises(ValueError, match="time-to-go"):
        ff(x, math.nan, u_nom)
    with pytest.raises(ValueError, match="dt"):
        FleetFilterSettings(dt=0.0)
    for hold in (0.0, -0.2, math.nan, math.inf, "0.2"):
        with pytest.raises(ValueError, match="hold"):
            FleetFilterSettings(dt=0.05, hold=hold)
    for reaction in (-0.1, math.nan, math.inf, "0.5"):
        with pytest.raises(ValueError, match="reaction_time"):
            FleetFilterSettings(dt=0.05, reaction_time=reaction)
    # a nominal input beyond the turn bound is clipped, as SafetyFilter clips it
    _, info = ff(x, 1.0, torch.full((4, 3), 5.0, dtype=F64))
    assert bool((info.nominal == 1.1).all())


def test_a_non_finite_pair_value_is_refused():
    class Broken(Smooth):
        def value(self, x, t):
            return super().value(x, t) * math.nan

    system = fleet(3)
    ff = FleetFilter(FleetValue(system, Broken(RelativePair())), FleetFilterSettings(dt=0.05))
    with pytest.raises(ValueError, match="non-finite value or gradient"):
        ff(states(3, 4, 0.5, 0), 1.0, nominal(3, 4, 0, 1.0))


def test_absent_cars_take_part_in_no_pair(pair):
    ff = FleetFilter(FleetValue(fleet(3, 2.0), pair), FleetFilterSettings(dt=0.05))
    x = pinch()
    present = torch.tensor([[True, True, False]])
    u, info = ff(x, 1.0, torch.zeros(1, 3, dtype=F64), present)
    assert int(info.solved[0]) == 0 and int(info.conflicts[0]) == 1  # a lone pair now: the switch rule
    assert not bool(info.intervened[0, 2]) and float(u[0, 2]) == 0.0


def test_the_fleet_rules_refuse_a_wrong_value_or_settings_naming_it(pair):
    fv = FleetValue(fleet(3, 2.0), pair)
    for rule in (FleetFilter, NaiveUnionSwitch):
        with pytest.raises(ValueError, match="needs a FleetValue, got GridSolution"):
            rule(pair, FleetFilterSettings(dt=0.05))
        with pytest.raises(ValueError, match="must be a FleetFilterSettings, got dict"):
            rule(fv, {"dt": 0.05})


def test_the_reaction_time_sets_the_default_threshold_where_it_exceeds_one_step(pair):
    """The default threshold is the larger of the one-step default and ``reaction_time`` seconds of
    the pair's closing speed: twice the reaction time doubles it where it dominates, zero leaves the
    one-step default, and a threshold given outright ignores it."""
    from safety.fleet.filter import REACTION_TIME, pair_thresholds

    fv = FleetValue(fleet(3), pair)
    speed = fv.speed_sum[0, 1]
    base = pair_thresholds(fv, FleetFilterSettings(dt=0.05))
    assert torch.allclose(base[0, 1], REACTION_TIME * speed)
    longer = pair_thresholds(fv, FleetFilterSettings(dt=0.05, reaction_time=2 * REACTION_TIME))
    assert torch.allclose(longer, 2 * base)
    one_step = pair_thresholds(fv, FleetFilterSettings(dt=0.05, reaction_time=0.0))
    assert bool((one_step < base).all()) and bool((one_step > 0).all())
    given_ = pair_thresholds(fv, FleetFilterSettings(dt=0.05, threshold=0.3, reaction_time=3.0))
    assert bool((given_ == 0.3).all())


def test_leximin_breaks_exact_ties_of_the_least_score_by_the_next_least():
    from safety.fleet.greedy import leximin_best  # lazy: only these tests call the tie-break alone

    # two groups: pairs 0-2 in group 0, pairs 3-4 in group 1; four candidates (rows)
    scores = torch.tensor(
        [
            [0.1, 0.5, 0.9, 0.3, 0.3],  # group 0: (0.1, 0.5, 0.9); group 1: (0.3, 0.3)
            [0.1, 0.6, 0.2, 0.3, 0.4],  # (0.1, 0.2, 0.6) loses to row 0 at the second; (0.3, 0.4) wins group 1
            [0.1, 0.6, 0.7, 0.2, 0.9],  # (0.1, 0.6, 0.7): the best of group 0
            [0.1, 0.6, 0.7, 0.3, 0.4],  # the same as rows 2 and 1: ties go to the first
        ],
        dtype=F64,
    )
    group = torch.tensor([0, 0, 0, 1, 1])
    least = torch.full((4, 2), math.inf, dtype=F64).scatter_reduce(1, group.expand(4, -1), scores, reduce="amin")
    assert leximin_best(scores, group, least).tolist() == [2, 1]
    assert least.argmax(0).tolist() == [0, 0]  # the centre rule: the first of the tied least


def test_the_greedy_leximin_takes_the_held_input_whose_sorted_pair_scores_are_highest(pair):
    import itertools  # lazy: only this brute force enumerates the candidates

    from safety.fleet.greedy import LEXIMIN_LEVELS  # lazy: as above

    # four cars in one infeasible conflict, where the centre rule keeps all four straight
    x = torch.tensor([[-0.32, -0.69, 0.29, -0.12, 0.39, 0.23, -0.19, 0.38, -0.99, -1.03, -0.89, -0.37]], dtype=F64)
    fv = FleetValue(fleet(4, 2.0), pair)
    nominal = torch.zeros(1, 4, dtype=F64)
    centre = FleetFilter(fv, FleetFilterSettings(dt=0.05))
    leximin = FleetFilter(fv, FleetFilterSettings(dt=0.05, tie_break="leximin"))
    u_centre, info = centre(x, 1.0, nominal)
    u, _ = leximin(x, 1.0, nominal)
    assert int(info.infeasible[0]) == 1 and bool(info.intervened.all())
    c = fv.candidates(x, 1.0, level=centre.level)
    active = c.value <= centre.level[c.first, c.second]
    pairs = [(int(i), int(j)) for i, j in zip(c.first[active], c.second[active])]

    def sorted_scores(w: torch.Tensor) -> list[float]:
        held = [float(_held_score(pair, _rel(x, 4, i, j), torch.stack([w[i], w[j]])[None], 1.0)[0]) for i, j in pairs]
        return sorted(held)[: LEXIMIN_LEVELS + 2]

    options = [torch.zeros(4, dtype=F64)] + [
        torch.tensor(s, dtype=F64) * 1.1 for s in itertools.product((-1, 1), repeat=4)
    ]
    best = max(sorted_scores(w) for w in options)
    assert sorted_scores(u[0]) == pytest.approx(best, abs=1e-12)
    assert torch.equal(u_centre[0], torch.zeros(4, dtype=F64))  # the centre rule: all straight
    assert sorted_scores(u_centre[0])[0] == pytest.approx(best[0], abs=1e-12)  # ... ties on the least
    assert sorted_scores(u_centre[0]) < best  # ... and loses on the next
    with pytest.raises(ValueError, match="tie_break"):
        FleetFilterSettings(dt=0.05, tie_break="random")
