"""A batched simulator of fleet scenes, the goal-seeking nominal policy and batched episode rollouts.

States follow :mod:`reach_envs.fleet_scenes`: ``x`` of shape ``(B, 3N)`` in
:class:`~reach.systems.multivehicle.MultiVehicle` order, goals ``(B, N, 2)``, and ``present`` ``(B, N)``
bool, the cars still in the scene. Inputs are physical turn rates ``(B, N)``, ``|w_i| <= w_max_i``.

:class:`FleetSimulator` advances a batch with the fleet's own ``MultiVehicle`` dynamics and the
library's stepper (:func:`reach.integrators.make_stepper`, RK4 by default), so the car model lives
in one place. It steps cars of one kind (speed, turn-rate bound) together: a MultiVehicle with one
car per kind runs on columns ``(B, cars of that kind)``, the same arithmetic per car as the N-car
system with a handful of tensor operations per stage instead of a few per car. A car that left the
scene (arrived or crashed) stays where it stopped and takes no part in collision checks. After each
step it judges, among the cars present before the step:

* **collided**: within ``collision_radius`` of another present car (both collide);
* **arrived**: within ``goal_radius`` of its goal and not collided (a car that reaches its goal in a
  collision has collided);

and both leave the scene: ``present_next = present & ~collided & ~arrived``.

Every entry point refuses, with a ``ValueError`` naming it, a wrong shape or dtype, NaN or inf, a goal
or presence mask that does not fit the batch, and a turn rate beyond its car's bound (by more than a
relative ``1e-9``, which is clamped away: a solver's rounding is not the caller's mistake).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from reach.integrators import INTEGRATORS, make_stepper
from reach.systems.arrays import TORCH
from reach.systems.multivehicle import Car, MultiVehicle
from reach_envs.fleet_scenes import FleetScene

#: a fleet controller: ``(x, goals, present) -> u``, turn rates ``(B, N)`` in physical units
Controller = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]

#: relative slack on the turn-rate bound that a solver's rounding may use (clamped away)
BOUND_TOLERANCE = 1e-9
#: the goal-seeking policy's heading time constant (seconds): turn rate = heading error / tau, clipped
HEADING_TIME = 0.25


class FleetSimulator:
    """Steps batches of fleet states of one :class:`~reach_envs.fleet_scenes.FleetScene`.

    Args:
        scene: the fleet scene (cars, radii, ``dt``).
        integrator: one of :data:`reach.integrators.INTEGRATORS`, ``"rk4"`` by default.
    """

    def __init__(self, scene: FleetScene, integrator: str = "rk4") -> None:
        if not isinstance(scene, FleetScene):
            raise ValueError(f"FleetSimulator: scene must be a FleetScene, got {type(scene).__name__}")
        if integrator not in INTEGRATORS:
            raise ValueError(f"FleetSimulator: integrator must be one of {INTEGRATORS}, got {integrator!r}")
        self.scene = scene
        #: the fleet as one N-car MultiVehicle (the filter's convention; the grouped stepper's reference)
        self.system = scene.system()
        self.n = scene.n_cars
        self.dt = scene.dt
        self.groups = car_groups(scene)
        self.kinds = kinds_system(scene, self.groups)
        self._step = make_stepper(self.kinds, scene.dt, integrator, TORCH)
        self._bound = torch.tensor(scene.max_turn_rates, dtype=torch.float64)

    # ------------------------------------------------------------------ checks
    def check_state(self, x: torch.Tensor, what: str = "x") -> torch.Tensor:
        """``x`` as float64 ``(B, 3N)``; anything else, or NaN/inf, raises ``ValueError`` naming it."""
        return _check_tensor(x, what, (None, 3 * self.n))

    def check_goals(self, goals: torch.Tensor, batch: int) -> torch.Tensor:
        """``goals`` as float64 ``(B, N, 2)``, finite."""
        return _check_tensor(goals, "goals", (batch, self.n, 2))

    def check_present(self, present: torch.Tensor, batch: int) -> torch.Tensor:
        """``present`` as a bool ``(B, N)`` tensor."""
        if not isinstance(present, torch.Tensor) or present.dtype != torch.bool:
            kind = present.dtype if isinstance(present, torch.Tensor) else type(present).__name__
            raise ValueError(f"present must be a bool torch tensor, got {kind}")
        if tuple(present.shape) != (batch, self.n):
            raise ValueError(f"present must have shape {(batch, self.n)}, got {tuple(present.shape)}")
        return present

    def check_inputs(self, u: torch.Tensor, batch: int) -> torch.Tensor:
        """Turn rates ``(B, N)``, finite and within each car's bound (a relative :data:`BOUND_TOLERANCE`
        over it is clamped); beyond raises ``ValueError`` naming the car and the rate."""
        u = _check_tensor(u, "u", (batch, self.n))
        bound = self._bound.to(u.device)
        over = u.abs() > bound * (1.0 + BOUND_TOLERANCE)
        if bool(over.any()):
            row, car = (int(i) for i in over.nonzero()[0])
            raise ValueError(
                f"u: turn rate {float(u[row, car])!r} of car_{car + 1} (episode {row}) is beyond its bound "
                f"{float(bound[car]):g}"
            )
        return torch.clamp(u, -bound, bound)

    # ------------------------------------------------------------------ physics
    def collisions(self, x: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """``(B, N)`` bool: present cars within ``collision_radius`` of another present car."""
        pos = positions(x, self.n)
        dist = torch.cdist(pos, pos, compute_mode="donot_use_mm_for_euclid_dist")
        live = present[:, :, None] & present[:, None, :]
        live = live & ~torch.eye(self.n, dtype=torch.bool, device=x.device)
        return ((dist <= self.scene.collision_radius) & live).any(dim=2)

    def arrivals(self, x: torch.Tensor, goals: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """``(B, N)`` bool: present cars within ``goal_radius`` of their goals."""
        gap = torch.linalg.vector_norm(positions(x, self.n) - goals, dim=-1)
        return present & (gap <= self.scene.goal_radius)

    def step(
        self, x: torch.Tensor, u: torch.Tensor, present: torch.Tensor, goals: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of ``dt``: ``(x_next, collided, arrived, present_next)``, each ``(B, ...)``.

        Present cars move under their turn rates ``u``; absent ones stay where they are (their ``u`` is
        checked but unused). ``collided`` and ``arrived`` are judged at ``x_next`` among the cars
        present before the step (module docstring)."""
        x = self.check_state(x)
        b = x.shape[0]
        present = self.check_present(present, b)
        goals = self.check_goals(goals, b)
        u = self.check_inputs(u, b)
        x_next = self.advance(x, u, present)
        collided = self.collisions(x_next, present)
        arrived = self.arrivals(x_next, goals, present) & ~collided
        return x_next, collided, arrived, present & ~collided & ~arrived

    def advance(self, x: torch.Tensor, u: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """The dynamics alone (inputs already checked): the stepper of :attr:`kinds`, whose every car
        is a group of identical cars (columns ``(B, size of the group)``), on present cars."""
        n, groups = self.n, self.groups
        columns = [x[:, 2 * g + k] for g in groups for k in (0, 1)] + [x[:, 2 * n + g] for g in groups]
        out = self._step(columns, [u[:, g] for g in groups], [])
        nxt = torch.empty_like(x)
        for k, g in enumerate(groups):  # a loop over kinds of car, a handful at most
            nxt[:, 2 * g], nxt[:, 2 * g + 1], nxt[:, 2 * n + g] = out[2 * k], out[2 * k + 1], out[2 * len(groups) + k]
        if not bool(torch.isfinite(nxt).all()):
            raise ValueError("FleetSimulator: the next state is NaN or infinite; check the inputs")
        keep = torch.cat([present.repeat_interleave(2, dim=1), present], dim=1)
        return torch.where(keep, nxt, x)


def car_groups(scene: FleetScene) -> list[torch.Tensor]:
    """The car indices of each kind (speed and turn-rate bound) of the scene, in order of first
    appearance; one kind is split in two halves, as a MultiVehicle has at least two cars."""
    kinds = list(zip(scene.speeds, scene.max_turn_rates))
    order = list(dict.fromkeys(kinds))
    groups = [torch.tensor([i for i, k in enumerate(kinds) if k == kind]) for kind in order]
    if len(groups) == 1:
        half = (scene.n_cars + 1) // 2
        groups = [groups[0][:half], groups[0][half:]]
    return groups


def kinds_system(scene: FleetScene, groups: list[torch.Tensor]) -> MultiVehicle:
    """A MultiVehicle with one car per group of identical cars: stepped on columns of shape
    ``(B, size of the group)``, it advances every car of the group at once with the same arithmetic as
    the N-car system (each car's dynamics read its own columns only)."""
    speeds, rates = scene.speeds, scene.max_turn_rates
    cars = [Car(speeds[int(g[0])], rates[int(g[0])], "control", f"kind_{k + 1}") for k, g in enumerate(groups)]
    return MultiVehicle(cars, collision_radius=scene.collision_radius, half_width=scene.extent)


def positions(x: torch.Tensor, n: int) -> torch.Tensor:
    """Car positions ``(B, N, 2)`` of fleet states ``(B, 3N)``."""
    return x[:, : 2 * n].reshape(x.shape[0], n, 2)


def headings(x: torch.Tensor, n: int) -> torch.Tensor:
    """Car headings ``(B, N)`` of fleet states ``(B, 3N)``."""
    return x[:, 2 * n :]


def _check_tensor(value: torch.Tensor, what: str, shape: tuple[int | None, ...]) -> torch.Tensor:
    """``value`` as a float64 tensor of ``shape`` (``None``: any size >= 1), all finite."""
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{what} must be a torch tensor, got {type(value).__name__}")
    if not value.dtype.is_floating_point:
        raise ValueError(f"{what} must be a floating-point tensor, got {value.dtype}")
    got = tuple(value.shape)
    if len(got) != len(shape) or any(s is not None and g != s for g, s in zip(got, shape)) or 0 in got:
        want = tuple("B" if s is None else s for s in shape)
        raise ValueError(f"{what} must have shape {want}, got {got}")
    value = value.to(torch.float64)
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{what} contains a non-finite value (NaN or inf)")
    return value


def goal_seeking(x: torch.Tensor, goals: torch.Tensor, scene: FleetScene) -> torch.Tensor:
    """The nominal: each car steers its heading toward its goal, ``w = clip(e / tau, +-w_max)`` for
    heading error ``e`` and ``tau =`` :data:`HEADING_TIME`, turn rates ``(B, N)``.

    It steers at the goal from anywhere, not along the intersection's lanes: a car bound for a side
    arm cuts the corner. A goal inside the turning circle on the side the car would turn to cannot be reached by turning
    (the car would circle it forever), so there the car drives straight until the goal falls outside
    that circle, then turns onto it."""
    n = scene.n_cars
    x = _check_tensor(x, "x", (None, 3 * n))
    goals = _check_tensor(goals, "goals", (x.shape[0], n, 2))
    to_goal = goals - positions(x, n)
    th = headings(x, n)
    error = TORCH.wrap_angle(torch.atan2(to_goal[..., 1], to_goal[..., 0]) - th)
    w_max = torch.tensor(scene.max_turn_rates, dtype=torch.float64, device=x.device)
    radius = torch.tensor(scene.speeds, dtype=torch.float64, device=x.device) / w_max
    side = torch.where(error >= 0, 1.0, -1.0)  # +1: the centre of a left turn lies to the left
    centre = torch.stack([-torch.sin(th), torch.cos(th)], dim=-1) * (side * radius)[..., None]
    inside = torch.linalg.vector_norm(to_goal - centre, dim=-1) < radius
    w = torch.clamp(error / HEADING_TIME, -w_max, w_max)
    return torch.where(inside, torch.zeros_like(w), w)


@dataclass(frozen=True)
class FleetOutcome:
    """What a batch of episodes came to (tensors on the CPU; B episodes of N cars).

    Attributes:
        collided: ``(B, N)`` bool, cars that collided.
        arrival_time: ``(B, N)`` float64, the time each car arrived, NaN for one that never did.
        steps: steps simulated (the batch stops once no car is present, or at the horizon).
        states: ``(T + 1, B, 3N)`` states when the rollout recorded them, else ``None``.
        present: ``(T + 1, B, N)`` presence masks when recorded, else ``None``.
    """

    collided: torch.Tensor
    arrival_time: torch.Tensor
    steps: int
    states: torch.Tensor | None = None
    present: torch.Tensor | None = None

    @property
    def any_collision(self) -> torch.Tensor:
        """``(B,)`` bool: episodes with at least one collision."""
        return self.collided.any(dim=1)

    @property
    def arrived(self) -> torch.Tensor:
        """``(B, N)`` bool: cars that reached their goals."""
        return ~torch.isnan(self.arrival_time)

    @property
    def goal_rate(self) -> torch.Tensor:
        """``(B,)`` float64: the share of each episode's cars that reached their goals."""
        return self.arrived.to(torch.float64).mean(dim=1)


def rollout(
    scene: FleetScene,
    x0: torch.Tensor,
    goals: torch.Tensor,
    controller: Controller | None = None,
    record: bool = False,
) -> FleetOutcome:
    """Run a batch of episodes from ``x0`` ``(B, 3N)`` with ``goals`` ``(B, N, 2)`` until no car is
    present or the horizon ends; ``controller(x, goals, present) -> u`` picks the turn rates
    (:func:`goal_seeking` by default, a safety filter wrapping it for a filtered run). ``record=True``
    keeps every state and presence mask (a GIF's frames, :func:`reach_envs.fleet_render.render_fleet`)."""
    sim = FleetSimulator(scene)
    x = sim.check_state(x0, "x0")
    b = x.shape[0]
    goals = sim.check_goals(goals, b)
    if controller is None:

        def controller(x: torch.Tensor, goals: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
            return goal_seeking(x, goals, scene)

    present = torch.ones(b, sim.n, dtype=torch.bool)
    collided = torch.zeros(b, sim.n, dtype=torch.bool)
    arrival = torch.full((b, sim.n), math.nan, dtype=torch.float64)
    states, masks = ([x], [present]) if record else ([], [])
    steps = 0
    while steps < scene.max_steps and bool(present.any()):
        u = controller(x, goals, present)
        x, hit, arrived, present = sim.step(x, u, present, goals)
        steps += 1
        collided |= hit
        arrival = torch.where(arrived, steps * scene.dt, arrival)
        if record:
            states.append(x)
            masks.append(present)
    if not record:
        return FleetOutcome(collided, arrival, steps)
    return FleetOutcome(collided, arrival, steps, torch.stack(states), torch.stack(masks))
