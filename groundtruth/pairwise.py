"""Pairwise BRTs of a multi-vehicle system and their union, as a value function on the full state.

Two cars that cannot avoid each other on their own cannot do so with more cars around, so every
state in the union of the pairwise BRTs lies in the true multi-vehicle BRT. The union's value,
``min over failure pairs (i, j) of V_ij(relative state of j in i's frame, t)``, is therefore an
*outer* check of a learned value (a learned BRT that misses part of the union is provably wrong
there) and a decomposition safety filter in its own right.

Each pair's value comes from a 3D grid solution of :class:`~reach.systems.RelativePair` (car 2's
role = car j's role; car i is always a control car). Gradients on the full state are the pair
gradient pulled back through the relative-coordinate map (autograd on that small map only).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import torch

from groundtruth.settings import SolverSettings
from groundtruth.solution import GridSolution
from groundtruth.solver import solve
from reach.systems import TORCH, MultiVehicle, RelativePair, system_from_config


def pair_system(system: MultiVehicle, i: int, j: int, half_width: float = 1.6) -> RelativePair:
    """The two-car problem of cars ``i`` (a control car) and ``j`` in ``i``'s frame."""
    a, b = system.cars[i], system.cars[j]
    if a.role != "control":
        raise ValueError(f"pair ({i}, {j}): car {i} must be a control car (roles {a.role}, {b.role})")
    return RelativePair(
        speed_1=a.speed,
        speed_2=b.speed,
        max_turn_rate_1=a.max_turn_rate,
        max_turn_rate_2=b.max_turn_rate,
        role_2=b.role,
        collision_radius=system.collision_radius,
        horizon=system.horizon,
        half_width=half_width,
    )


def relative_state(p_i: torch.Tensor, p_j: torch.Tensor, th_i: torch.Tensor, th_j: torch.Tensor) -> torch.Tensor:
    """``(..., 3)``: car ``j`` relative to car ``i`` in ``i``'s frame, ``(c dx + s dy, -s dx + c dy,
    th_j - th_i)`` (heading wrapped), from positions ``(..., 2)`` and headings ``(...)``: the state of
    their :class:`~reach.systems.RelativePair` (shared by :class:`PairwiseUnion` and :mod:`safety.fleet`)."""
    dx = p_j[..., 0] - p_i[..., 0]
    dy = p_j[..., 1] - p_i[..., 1]
    c, s = torch.cos(th_i), torch.sin(th_i)
    return torch.stack([c * dx + s * dy, -s * dx + c * dy, TORCH.wrap_angle(th_j - th_i)], dim=-1)


def pull_back(
    grad: torch.Tensor, rel: torch.Tensor, th_i: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A pair gradient ``grad = (g0, g1, g2)`` at relative state ``rel`` pulled back to the full
    state: ``(gx, gy, g_th_i, g_th_j)``, car ``j``'s position components (car ``i``'s are their
    negatives) and the two headings' (see :meth:`PairwiseUnion.gradient`). The heading components are
    also the pair's switching functions: ``d V / dt`` gains ``g_th_i w_i + g_th_j w_j``."""
    g0, g1, g2 = grad[..., 0], grad[..., 1], grad[..., 2]
    c, s = torch.cos(th_i), torch.sin(th_i)
    return g0 * c - g1 * s, g0 * s + g1 * c, g0 * rel[..., 1] - g1 * rel[..., 0] - g2, g2


def _ordered_pairs(system: MultiVehicle) -> list[tuple[int, int]]:
    """Failure pairs with the control car first."""
    return [(i, j) if system.cars[i].role == "control" else (j, i) for i, j in system.failure_pairs]


def solve_pairs(
    system: MultiVehicle,
    grid: int | Sequence[int] = 81,
    times: Sequence[float] | None = None,
    half_width: float = 1.6,
    *,
    settings: SolverSettings | None = None,
    progress: bool = True,
) -> dict[RelativePair, GridSolution]:
    """Grid solutions of every distinct pair problem (one for the 9D system: its cars are identical).

    ``times`` default to 11 evenly spaced times over the horizon (the union interpolates between them);
    ``settings`` and ``progress`` go to every :func:`~groundtruth.solver.solve`.
    """
    times = list(times) if times is not None else [system.horizon * k / 10 for k in range(11)]
    out: dict[RelativePair, GridSolution] = {}
    for i, j in _ordered_pairs(system):
        pair = pair_system(system, i, j, half_width)
        if pair not in out:
            out[pair] = solve(pair, grid, times, settings=settings, progress=progress)
            out[pair].outside = "clamp"
    return out


class PairwiseUnion:
    """``V(x, t) = min over failure pairs of V_pair(relative state, t)`` on a multi-vehicle state.

    Args:
        system: the multi-vehicle system.
        solutions: grid solutions of its pair problems (``solve_pairs``), or one solution used for
            every pair whose problem equals that solution's system.

    Relative positions beyond a pair grid's box use its edge value (``outside="clamp"``): such cars
    are at least ``half_width`` apart, farther than the cars can close within the horizon. Pairs
    match solutions by physics (:meth:`physics_config`), and the union's ``system`` is the given one
    with the horizon of its solutions, so it can filter a longer scene of the same cars.
    """

    def __init__(self, system: MultiVehicle, solutions: GridSolution | dict[RelativePair, GridSolution]) -> None:
        if not isinstance(system, MultiVehicle):
            raise ValueError(f"PairwiseUnion needs a multi-vehicle system, got {system.name}")
        if isinstance(solutions, GridSolution):
            solutions = {solutions.system: solutions}
        self.pairs = _ordered_pairs(system)
        self._boxes: dict[tuple[torch.dtype, torch.device], tuple[torch.Tensor, ...]] = {}
        self._solutions = []
        for i, j in self.pairs:
            wanted = pair_system(system, i, j).physics_config()
            match = [s for pair, s in solutions.items() if pair.physics_config() == wanted]
            if not match:
                raise ValueError(
                    f"no pair solution for cars ({i}, {j}) of {system.config()}; have {[p.config() for p in solutions]}"
                )
            match[0].outside = "clamp"
            self._solutions.append(match[0])
        # the union is a value function up to the horizon its pair solutions reach
        horizon = min(float(sol.times[-1]) for sol in self._solutions)
        config = system.config()
        config["parameters"] = {**config["parameters"], "horizon": horizon}
        self.system = system_from_config(config) if "horizon" in system.parameters() else system

    @property
    def time_range(self) -> tuple[float, float]:
        """The times-to-go every pair solution stores."""
        return (max(s.time_range[0] for s in self._solutions), min(s.time_range[1] for s in self._solutions))

    def relative_states(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., pairs, 3)``: car j relative to car i, in i's frame, for each failure pair."""
        n = self.system.num_cars
        out = [
            relative_state(x[..., 2 * i : 2 * i + 2], x[..., 2 * j : 2 * j + 2], x[..., 2 * n + i], x[..., 2 * n + j])
            for i, j in self.pairs
        ]
        return torch.stack(out, dim=-2)

    def _per_pair(self, method: str, rel: torch.Tensor, t: float | torch.Tensor, checked: bool = True):
        """``method`` (``"value"`` or ``"value_and_gradient"``) of each pair's solution at its relative
        state ``rel[..., k, :]``, stacked over the pairs. Where every pair shares one solution (the
        usual case: identical cars) it is one interpolation over all pairs at once, not one per pair."""
        more = {} if checked else {"checked": False}  # only value() takes it
        if all(sol is self._solutions[0] for sol in self._solutions):
            tt = t
            if isinstance(t, torch.Tensor) and t.ndim:  # a time per state: the same for each of its pairs
                tt = t.unsqueeze(-1).expand(rel.shape[:-1])
            return getattr(self._solutions[0], method)(rel, tt, **more)
        out = [getattr(sol, method)(rel[..., k, :], t, **more) for k, sol in enumerate(self._solutions)]
        if method == "value":
            return torch.stack(out, dim=-1)
        return torch.stack([v for v, _ in out], dim=-1), torch.stack([g for _, g in out], dim=-2)

    def pair_values(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """``(..., pairs)`` pairwise values."""
        return self._per_pair("value", self.relative_states(x), t)

    def value(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        self._check(x)
        return self.pair_values(x, t).min(dim=-1).values

    def gradient(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """The gradient of the minimising pair's value, pulled back to the full state.

        The pull-back is written out: with ``(dx, dy)`` car ``j``'s offset from car ``i`` and ``th``
        car ``i``'s heading, the relative state is ``(c dx + s dy, -s dx + c dy, th_j - th)``, so a
        pair gradient ``(g0, g1, g2)`` gives car ``j``'s position ``(g0 c - g1 s, g0 s + g1 c)``, car
        ``i``'s the negative, ``th_j`` ``g2`` and ``th`` ``-g2 + g0 r1 - g1 r0`` (``r`` the relative
        state; :func:`pull_back`). Tested against autograd through :meth:`relative_states`.
        """
        self._check(x)
        rel = self.relative_states(x)
        values, grads = self._per_pair("value_and_gradient", rel, t)
        best = values.argmin(dim=-1)
        n = self.system.num_cars
        g = torch.zeros_like(x)
        for k, (i, j) in enumerate(self.pairs):
            active = (best == k).to(grads.dtype)
            gx, gy, g_th_i, g_th_j = pull_back(
                grads[..., k, :] * active.unsqueeze(-1), rel[..., k, :], x[..., 2 * n + i]
            )
            g[..., 2 * j] += gx
            g[..., 2 * j + 1] += gy
            g[..., 2 * i] -= gx
            g[..., 2 * i + 1] -= gy
            g[..., 2 * n + j] += g_th_j
            g[..., 2 * n + i] += g_th_i
        return g

    def value_where_known(self, x: torch.Tensor, t: float | torch.Tensor, checked: bool = True) -> torch.Tensor:
        """The union's value using only the pairs whose relative state lies inside their grid's box;
        ``+inf`` where none does. An upper bound of the multi-vehicle value that never rests on a
        clamped edge value (which under-states a pair's value beyond the box): what a training
        penalty may push a network below. ``checked=False``: as :meth:`GridSolution.value`'s, for a
        captured training step's own points only."""
        if checked:
            self._check(x)
        rel = self.relative_states(x)
        low, high, periodic = self._grid_boxes(rel.dtype, rel.device)
        inside = (periodic | ((rel >= low) & (rel <= high))).all(-1)  # (..., pairs)
        values = self._per_pair("value", rel, t, checked)
        return torch.where(inside, values, torch.full_like(values, torch.inf)).min(dim=-1).values

    def _grid_boxes(self, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, ...]:
        """Each pair grid's ``(low, high, periodic)``, shape ``(pairs, 3)``, built once per dtype and
        device rather than copied there on every call."""
        key = (dtype, device)
        if key not in self._boxes:
            grids = [sol.grid for sol in self._solutions]
            self._boxes[key] = (
                torch.tensor([g.low for g in grids], dtype=dtype, device=device),
                torch.tensor([g.high for g in grids], dtype=dtype, device=device),
                torch.tensor([g.periodic for g in grids], device=device),
            )
        return self._boxes[key]

    @classmethod
    def load(cls, system: MultiVehicle, path: str | os.PathLike) -> PairwiseUnion:
        """The union from a pair grid solution file (``reach groundtruth relativepair``); a file of
        another problem, or a system that is not multi-vehicle, raises ``ValueError`` naming it."""
        solution = GridSolution.load(path, outside="clamp")
        if not isinstance(solution.system, RelativePair):
            what = solution.system.name
            raise ValueError(f"{path}: a grid solution of {what}, not of a two-car (relativepair) problem")
        return cls(system, solution)

    def _check(self, x: torch.Tensor) -> None:
        if x.ndim == 0 or x.shape[-1] != self.system.state_dim:
            raise ValueError(f"states must have shape (..., {self.system.state_dim}), got {tuple(x.shape)}")
        if not bool(torch.isfinite(x).all()):
            raise ValueError("states contain NaN or inf")
