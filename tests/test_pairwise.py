"""The union of pairwise BRTs: invariances, containment logic, and its policy keeping two cars apart."""

from __future__ import annotations

import math

import pytest
import torch

from groundtruth.pairwise import PairwiseUnion, pair_system
from reach.systems import Car, MultiVehicle, MultiVehicle9D, MultiVehicle12D, MultiVehicle15D
from safety import rollout
from safety.value_loading import load_value_function


def _rigid_motion(x: torch.Tensor, angle: float, shift: tuple[float, float], n: int) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    y = x.clone()
    for i in range(n):
        px, py = x[..., 2 * i], x[..., 2 * i + 1]
        y[..., 2 * i] = c * px - s * py + shift[0]
        y[..., 2 * i + 1] = s * px + c * py + shift[1]
        y[..., 2 * n + i] = torch.remainder(x[..., 2 * n + i] + angle + math.pi, 2 * math.pi) - math.pi
    return y


def test_pair_solution_is_the_nine_d_pair_problem(pair_grid):
    system = MultiVehicle9D()
    assert pair_grid.system == pair_system(system, 0, 1)
    assert pair_grid.system.control_dim == 2 and pair_grid.system.disturbance_dim == 0


def test_union_is_invariant_under_rigid_motions(pair_grid):
    system = MultiVehicle9D()
    union = PairwiseUnion(system, pair_grid)
    x = system.sample_states(500, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.6
    for angle, shift in ((0.7, (0.1, -0.2)), (-2.5, (0.0, 0.3)), (math.pi, (0.0, 0.0))):
        y = _rigid_motion(x, angle, shift, 3)
        rel_x, rel_y = union.relative_states(x), union.relative_states(y)
        assert torch.allclose(rel_x[..., :2], rel_y[..., :2], atol=1e-9)
        dth = torch.remainder(rel_x[..., 2] - rel_y[..., 2] + math.pi, 2 * math.pi) - math.pi
        assert dth.abs().max() < 1e-9
        assert torch.allclose(union.value(x, 1.0), union.value(y, 1.0), atol=1e-6)


def test_union_is_symmetric_under_relabelling(pair_grid):
    system = MultiVehicle9D()
    union = PairwiseUnion(system, pair_grid)
    x = system.sample_states(2000, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    v = union.value(x, 1.0)
    for perm in ((1, 0, 2), (2, 1, 0), (1, 2, 0)):
        idx = [2 * p + k for p in perm for k in (0, 1)] + [6 + p for p in perm]
        w = union.value(x[:, idx], 1.0)
        # relabelling swaps which car's frame a pair is seen from; the grid's two frames of one pair
        # agree up to its interpolation error near the BRT (far away, the clamped edges of the
        # 3.2 x 3.2 pair box differ, but there both values are large and positive)
        near = v < 0.5
        assert (w[near] - v[near]).abs().max() < 0.03
        assert (w[~near] > 0.4).all()
        assert ((w <= 0) == (v <= 0)).float().mean() > 0.995


def test_head_on_cars_are_in_the_union(pair_grid):
    union = PairwiseUnion(MultiVehicle9D(), pair_grid)
    # cars 1 and 2 head-on 0.4 apart (closing at 1.2/s), car 3 far away: a pairwise collision
    x = torch.tensor([[-0.2, 0.0, 0.2, 0.0, 0.9, 0.9, 0.0, math.pi - 1e-6, 0.0]], dtype=torch.float64)
    assert float(union.value(x, 1.0)) <= 0
    assert int(union.pair_values(x, 1.0).argmin()) == 0  # the (1, 2) pair is the minimiser
    # and the union is never above l(x): the pair values start from the pair margins
    y = MultiVehicle9D().sample_states(1000, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    assert (union.value(y, 1.0) <= MultiVehicle9D().failure_margin(y) + 0.02).all()


@pytest.mark.parametrize("system", [MultiVehicle12D(), MultiVehicle15D()], ids=lambda s: s.name)
def test_one_pair_grid_bounds_every_pair_of_the_larger_fleets(pair_grid, system):
    """The 12D and 15D fleets share the 9D pair problem: one pair grid serves their 6 and 10 pairs, and
    the union is the minimum over all of them (two cars head-on make it negative wherever they are)."""
    union = PairwiseUnion(system, pair_grid)
    n = system.num_cars
    assert len(system.failure_pairs) == n * (n - 1) // 2
    assert all(pair_system(system, i, j) == pair_system(MultiVehicle9D(), 0, 1) for i, j in system.failure_pairs)
    x = system.sample_states(500, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    pairs = union.pair_values(x, 1.0)
    assert pairs.shape == (500, len(system.failure_pairs))
    assert torch.equal(union.value(x, 1.0), pairs.min(dim=-1).values)
    assert (union.value(x, 1.0) <= system.failure_margin(x) + 0.02).all()
    # the last two cars head-on 0.4 apart, every other car far off in a corner: only their pair is unsafe
    far = torch.zeros(1, 3 * n, dtype=torch.float64)
    for i in range(n - 2):
        far[0, 2 * i], far[0, 2 * i + 1] = -0.9 + 0.6 * i, 0.9
    a, b = n - 2, n - 1
    far[0, 2 * a], far[0, 2 * b] = -0.2, 0.2
    far[0, 2 * n + b] = math.pi - 1e-6
    k = system.failure_pairs.index((a, b))
    assert float(union.value(far, 1.0)) <= 0 and int(union.pair_values(far, 1.0).argmin()) == k


def test_two_cars_under_pairwise_policy_do_not_collide(pair_grid):
    two = MultiVehicle([Car(0.6, 1.1, "control"), Car(0.6, 1.1, "control")], horizon=1.0)
    union = PairwiseUnion(two, pair_grid)
    x = two.sample_states(4000, generator=torch.Generator().manual_seed(3))
    v = union.value(x, 1.0)
    start = x[v > 0.05]
    assert start.shape[0] > 1000
    result = rollout(union, start, progress=False)
    assert int(result.collided.sum()) == 0
    inside = x[(v < -0.05) & (two.failure_margin(x) > 0)]
    assert inside.shape[0] > 20
    assert rollout(union, inside, progress=False).collided.float().mean() > 0.9


def test_pair_npz_loads_as_union_for_nine_d(pair_grid, tmp_path):
    path = tmp_path / "pair.npz"
    pair_grid.save(path)
    loaded = load_value_function(path, system="multivehicle9d")
    assert loaded.kind == "pairwise" and isinstance(loaded.value_function, PairwiseUnion)
    x = MultiVehicle9D().sample_states(10)
    assert loaded.value_function.gradient(x, 1.0).shape == (10, 9)
    with pytest.raises(ValueError, match="NaN or inf"):
        loaded.value_function.value(torch.full((1, 9), float("nan")), 1.0)


def test_union_overlay_plot_and_slice_parsing(pair_grid, tmp_path):
    from reach.systems.multivehicle import DEEPREACH_9D_SLICE
    from reach_cli import main
    from studies.plots import eval_number, parse_slice
    from training import ValueNetwork, save_checkpoint

    assert eval_number("3pi/4") == pytest.approx(3 * math.pi / 4) and eval_number("-pi") == -math.pi
    spec = parse_slice("x2=-0.5,th1=pi/4;x1,y1", MultiVehicle9D())
    assert spec.axes == (0, 1) and spec.base[2] == -0.5 and spec.base[6] == pytest.approx(math.pi / 4)
    assert spec.base[4] == DEEPREACH_9D_SLICE[4]
    with pytest.raises(ValueError, match="unknown state name"):
        parse_slice("q=1;x1,y1", MultiVehicle9D())
    pair = tmp_path / "pair.npz"
    pair_grid.save(pair)
    ckpt = tmp_path / "net.pt"
    save_checkpoint(ckpt, ValueNetwork(MultiVehicle9D(), "ssrsl", width=16))
    out = tmp_path / "union.png"
    args = ["plot", "union", str(ckpt), str(pair), "--system", "multivehicle9d", "--pairwise", str(pair)]
    assert main([*args, "--slice", "th1=0;x1,y1", "--slice", ";x1,y1", "--out", str(out)]) == 0
    assert out.stat().st_size > 5000


def test_the_2021_figure_slice_is_drawn_and_its_cars_sit_in_the_union(pair_grid):
    from reach.systems.multivehicle import PAPER_2021_9D_SLICE
    from studies.plots import default_slices

    system = MultiVehicle9D()
    assert [s.base for s in default_slices(system)].count(PAPER_2021_9D_SLICE) == 1
    union = PairwiseUnion(system, pair_grid)
    x = torch.tensor([PAPER_2021_9D_SLICE] * 3)
    x[0, :2] = torch.tensor([-0.4, 0.0])  # car 1 on car 2
    x[1, :2] = torch.tensor([0.43, 0.33])  # car 1 on car 3
    x[2, :2] = torch.tensor([0.0, -0.9])  # car 1 far below both, heading away (-2.54 rad)
    v = union.value(x, 1.0)
    assert v[0] <= 0 and v[1] <= 0 and v[2] > 0


def test_network_capped_by_the_union_misses_none_of_it_and_follows_the_active_gradient(pair_grid, tmp_path):
    """min(V_net, V_union): never above either member, unsafe wherever the union is (no misses),
    the gradient of whichever member is smaller, loadable as a "min:RUN,pair.npz" source."""
    from reach.value_function import MinimumOf, value_and_gradient
    from training import TrainConfig, Trainer
    from training.network import NeuralValueFunction
    from training.trainer import build_network

    system = MultiVehicle9D()
    union = PairwiseUnion(system, pair_grid)
    net = NeuralValueFunction(build_network(TrainConfig(system="multivehicle9d", width=16, steps=1)))
    capped = MinimumOf(net, union)
    x = system.sample_states(400, generator=torch.Generator().manual_seed(3)) * 0.5
    t = 0.8
    v, g = capped.value_and_gradient(x, t)
    vn, gn = value_and_gradient(net, x, t)
    vu, gu = union.value(x, t), union.gradient(x, t)
    assert torch.equal(v, torch.minimum(vn, vu))
    assert bool(((vu <= 0) <= (v <= 0)).all())  # every state the union calls unsafe stays unsafe
    active = capped.active(x, t)
    assert 0 < int(active.sum()) < len(x)  # both members are active somewhere: the test sees both
    torch.testing.assert_close(g, torch.where(active[:, None] == 1, gu, gn))
    with pytest.raises(ValueError, match="at least two"):
        MinimumOf(net)
    with pytest.raises(ValueError, match="member 1"):
        MinimumOf(net, load_value_function(_air3d_grid(tmp_path)).value_function)
    with pytest.raises(ValueError, match="lies outside"):
        capped.value(x, 1.5)

    run = tmp_path / "run"
    Trainer(
        TrainConfig(system="multivehicle9d", width=16, points=64, steps=2, checkpoint_every_s=0.0), run, progress=False
    ).train()
    pair = tmp_path / "pair.npz"
    pair_grid.save(pair)
    loaded = load_value_function(f"min:{run},{pair}")
    assert loaded.kind == "min" and loaded.label == "min(run, pair)"
    assert isinstance(loaded.value_function.members[1], PairwiseUnion)
    with pytest.raises(ValueError, match="at least two sources"):
        load_value_function(f"min:{run}")

    # "cap:": the same capped value, steered by the network's gradient everywhere (the union's gradient
    # leaves the third car driving straight); the union's gradient is then never taken
    def no_gradient(*args):
        raise AssertionError("the union's gradient was taken")

    blind = PairwiseUnion(system, pair_grid)
    blind.gradient = blind.value_and_gradient = no_gradient
    steered = MinimumOf(net, blind, steer_by=0)
    vs, gs = steered.value_and_gradient(x, t)
    assert torch.equal(vs, v) and torch.equal(gs, gn) and not torch.equal(gs, g)
    loaded = load_value_function(f"cap:{run},{pair}")
    assert loaded.kind == "cap" and loaded.label == "cap(run, pair)" and loaded.value_function.steer_by == 0
    with pytest.raises(ValueError, match="do not nest"):
        load_value_function(f"cap:{run},min:{run},{pair}")
    for bad in (2, -1, True, 0.0):
        with pytest.raises(ValueError, match="steer_by"):
            MinimumOf(net, union, steer_by=bad)


def _air3d_grid(tmp_path):
    from groundtruth import SolverSettings, solve
    from reach.systems import Air3D

    path = tmp_path / "air3d.npz"
    solve(Air3D(), 11, [0.0, 1.0], settings=SolverSettings(compile=False), progress=False).save(path)
    return path


def test_the_union_where_known_drops_pairs_beyond_their_grid(pair_grid):
    """value_where_known agrees with the union where every pair lies inside its grid, skips a pair
    beyond it (whose clamped edge value would under-state it), and is +inf where none is inside."""
    system = MultiVehicle9D()
    union = PairwiseUnion(system, pair_grid)
    x = system.sample_states(3000, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.4
    assert torch.allclose(union.value_where_known(x, 1.0), union.value(x, 1.0))
    far = x.clone()
    far[:, 4] += 10.0  # car 2 far away in x: pairs (0, 2) and (1, 2) leave their grids
    values = union.pair_values(far, 1.0)
    pair_01 = union.pairs.index((0, 1))
    assert torch.allclose(union.value_where_known(far, 1.0), values[:, pair_01])
    apart = far.clone()
    apart[:, 2] -= 10.0  # car 1 far away in the other direction: no pair inside
    assert torch.isinf(union.value_where_known(apart, 1.0)).all()


def test_union_gradient_is_the_autograd_pull_back_of_the_active_pair(pair_grid):
    """The written-out pull-back equals autograd through relative_states, for one time and for a
    time per state (which the batched interpolation over the pairs must spread to each pair)."""
    system = MultiVehicle9D()
    union = PairwiseUnion(system, pair_grid)
    x = system.sample_states(300, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 0.5
    for t in (0.7, torch.linspace(0.1, 1.0, len(x), dtype=torch.float64)):
        xg = x.clone().requires_grad_(True)
        rel = union.relative_states(xg)
        pairs = [pair_grid.value_and_gradient(rel.detach()[:, k], t) for k in range(len(union.pairs))]
        values = torch.stack([v for v, _ in pairs], -1)
        grads = torch.stack([g for _, g in pairs], -2)
        mask = torch.nn.functional.one_hot(values.argmin(-1), len(union.pairs)).to(x.dtype).unsqueeze(-1)
        (want,) = torch.autograd.grad(rel, xg, grad_outputs=grads * mask)
        torch.testing.assert_close(union.gradient(x, t), want, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(union.pair_values(x, t), values, rtol=0, atol=0)
        assert int((values.argmin(-1)[:, None] == torch.arange(3)).sum(0).min()) > 0  # every pair active somewhere
