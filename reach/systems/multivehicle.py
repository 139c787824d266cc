"""A family of N Dubins cars, each either a control (keeps safe) or a disturbance (attacks).

Car ``i`` has state ``(x_i, y_i, th_i)`` and moves as ``x_i' = v_i cos th_i``, ``y_i' = v_i sin th_i``,
``th_i' = w_i`` with ``|w_i| <= w_max_i``. The state is ordered as DeepReach orders it: all positions
first, then all headings, ``(x_1, y_1, ..., x_N, y_N, th_1, ..., th_N)``. Control inputs are the turn
rates of the control cars in car order; disturbance inputs those of the disturbance cars.

The failure set is any pair of cars closer than ``collision_radius`` where at least one car is a
control car (collisions among disturbance cars are not the controller's failure):
``l(x) = min over such pairs of ||p_i - p_j|| - R``.

Named instances: :class:`MultiVehicle6D` (the Air3D game in absolute coordinates),
:class:`MultiVehicle9D` (DeepReach's three cooperating cars) and its larger siblings
:class:`MultiVehicle12D` and :class:`MultiVehicle15D` (four and five such cars).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch

from reach.systems.arrays import Backend, Column, InputMatrix
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Box
from reach.systems.deepreach_normalisation import DeepReachNormalisation
from reach.validation import positive_finite

ROLES = ("control", "disturbance")


@dataclass(frozen=True)
class Car:
    """One Dubins car: constant speed, bounded turn rate, and who drives its turn rate."""

    speed: float
    max_turn_rate: float
    role: str = "control"
    name: str = ""

    def __post_init__(self) -> None:
        for field in ("speed", "max_turn_rate"):
            value = getattr(self, field)
            positive_finite(f"Car {self.name or '?'}: {field}", value)
        if not isinstance(self.name, str):
            raise ValueError(f"Car: name must be a string, got {self.name!r}")
        if not isinstance(self.role, str) or self.role not in ROLES:
            raise ValueError(f"Car {self.name or '?'}: role must be one of {ROLES}, got {self.role!r}")


def _cars(cars: Any) -> tuple[Car, ...]:
    """``cars`` as a tuple of :class:`Car`, each given as one or as a mapping of its fields (a config's
    form); anything else is refused naming it."""
    if isinstance(cars, (str, bytes)) or not isinstance(cars, Sequence):
        raise ValueError(f"MultiVehicle: cars must be a list of Car (or of their fields), got {cars!r}")
    fields = {"speed", "max_turn_rate", "role", "name"}
    out = []
    for i, c in enumerate(cars):
        if isinstance(c, dict):
            if not (set(c) <= fields and {"speed", "max_turn_rate"} <= set(c)):
                raise ValueError(f"MultiVehicle: cars[{i}] must have speed, max_turn_rate (role, name), got {c!r}")
            c = Car(**c)
        if not isinstance(c, Car):
            raise ValueError(f"MultiVehicle: cars[{i}] must be a Car or a mapping of its fields, got {c!r}")
        out.append(c)
    return tuple(out)


class MultiVehicle(ControlAffineSystem):
    """N Dubins cars with roles; see the module docstring for state order and failure set."""

    name = "multivehicle"

    def __init__(
        self,
        cars: Sequence[Car],
        collision_radius: float = 0.25,
        horizon: float = 1.0,
        half_width: float = 1.0,
    ) -> None:
        cars = _cars(cars)
        if len(cars) < 2:
            raise ValueError(f"MultiVehicle: cars needs at least 2 cars, got {len(cars)}")
        if not any(c.role == "control" for c in cars):
            raise ValueError("MultiVehicle: cars needs at least one car with role 'control'")
        for field, value in (("collision_radius", collision_radius), ("horizon", horizon), ("half_width", half_width)):
            positive_finite(f"MultiVehicle: {field}", value)
        self.cars = tuple(
            c if c.name else Car(c.speed, c.max_turn_rate, c.role, f"car_{i + 1}") for i, c in enumerate(cars)
        )
        names = [c.name for c in self.cars]
        if len(set(names)) != len(names):
            raise ValueError(f"MultiVehicle: car names must be unique, got {names}")
        self.collision_radius = float(collision_radius)
        self.horizon = float(horizon)
        self.half_width = float(half_width)
        n = len(self.cars)
        self.state_names = tuple(f"{axis}{i + 1}" for i in range(n) for axis in ("x", "y")) + tuple(
            f"th{i + 1}" for i in range(n)
        )
        self.domain = ((-half_width, half_width),) * (2 * n) + ((-math.pi, math.pi),) * n
        self.periodic = (False,) * (2 * n) + (True,) * n
        self.control_cars = tuple(i for i, c in enumerate(self.cars) if c.role == "control")
        self.disturbance_cars = tuple(i for i, c in enumerate(self.cars) if c.role == "disturbance")
        self.control_bounds = Box.symmetric([self.cars[i].max_turn_rate for i in self.control_cars])
        self.disturbance_bounds = Box.symmetric([self.cars[i].max_turn_rate for i in self.disturbance_cars])
        self.failure_pairs = tuple(
            (i, j) for i in range(n) for j in range(i + 1, n) if "control" in (self.cars[i].role, self.cars[j].role)
        )
        self.deepreach = DeepReachNormalisation(
            state_offset=(0.0,) * (3 * n), state_scale=(1.0,) * (2 * n) + (1.2 * math.pi,) * n
        )
        self._control_entries = tuple((2 * n + car, k) for k, car in enumerate(self.control_cars))
        self._disturbance_entries = tuple((2 * n + car, k) for k, car in enumerate(self.disturbance_cars))

    def parameters(self) -> dict[str, Any]:
        return {
            "cars": [asdict(c) for c in self.cars],
            "collision_radius": self.collision_radius,
            "horizon": self.horizon,
            "half_width": self.half_width,
        }

    def physics_config(self) -> dict[str, Any]:
        """Cars (speed, turn bound, role, in order) and collision radius, whatever the subclass."""
        cars = [[c.speed, c.max_turn_rate, c.role] for c in self.cars]
        return {"name": "multivehicle", "parameters": {"cars": cars, "collision_radius": self.collision_radius}}

    @property
    def num_cars(self) -> int:
        return len(self.cars)

    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        n = len(self.cars)
        out: list[Column] = []
        for i, car in enumerate(self.cars):
            th = x[2 * n + i]
            out += [car.speed * xp.cos(th), car.speed * xp.sin(th)]
        return out + [0.0] * n

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        return {entry: 1.0 for entry in self._control_entries}

    def disturbance_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        return {entry: 1.0 for entry in self._disturbance_entries}

    def margin_rate_bound(self) -> float:
        """The largest ``v_i + v_j`` over failure pairs: how fast two cars at constant speeds can close."""
        return max(self.cars[i].speed + self.cars[j].speed for i, j in self.failure_pairs)

    def margin_floor(self, x: torch.Tensor, time: float) -> torch.Tensor:
        """A lower bound of ``l`` over the next ``time`` seconds under any turn rates, from the
        headings: cars that face away from each other must turn before they can close.

        For a pair at distance ``d`` along the unit vector ``e`` from car ``i`` to car ``j``, the
        distance at any later time is at least its projection on ``e``, ``d - D_i - D_j``, where
        ``D_i`` is the farthest car ``i`` can move along ``e`` (``-e`` for car ``j``) in that time.
        With heading ``a`` off ``e`` and turn bound ``w``, turning towards ``e`` at full rate is
        best: ``D = v/w (sin a - sin(a - w s))`` while it turns (``s <= a / w``), then straight on.
        ``D`` is convex in time, so the closest approach bound over ``[0, time]`` is
        ``d - max(0, D_i + D_j)`` at ``time``; an explicit Euler step moves a car along ``e`` by
        at most the integral over it (the integrand grows as the car turns), so held steps obey
        the bound too. Never below the default ``l - (v_i + v_j) time``."""
        n = self.num_cars
        floor = None
        for i, j in self.failure_pairs:
            dx, dy = x[..., 2 * j] - x[..., 2 * i], x[..., 2 * j + 1] - x[..., 2 * i + 1]
            toward = torch.atan2(dy, dx)
            closing = self._farthest_along(x[..., 2 * n + i] - toward, self.cars[i], time) + self._farthest_along(
                x[..., 2 * n + j] - toward - math.pi, self.cars[j], time
            )
            m = torch.hypot(dx, dy) - self.collision_radius - closing.clamp_min(0.0)
            floor = m if floor is None else torch.minimum(floor, m)
        return floor

    @staticmethod
    def _farthest_along(offset: torch.Tensor, car: Car, time: float) -> torch.Tensor:
        """The farthest a car can move along a direction ``offset`` radians off its heading in ``time``."""
        a = torch.remainder(offset + math.pi, 2 * math.pi) - math.pi
        a = a.abs()
        v, w = car.speed, car.max_turn_rate
        if w == 0:
            return v * time * torch.cos(a)
        turning = v / w * (torch.sin(a) - torch.sin(a - w * time))
        straight = v / w * torch.sin(a) + v * (time - a / w)
        return torch.where(w * time <= a, turning, straight)

    def pair_margin(self, x: Sequence[Column], i: int, j: int, xp: Backend) -> Column:
        """``||p_i - p_j|| - R`` for cars ``i`` and ``j``."""
        return xp.hypot(x[2 * i] - x[2 * j], x[2 * i + 1] - x[2 * j + 1]) - self.collision_radius

    def failure_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        margin: Column | None = None
        for i, j in self.failure_pairs:
            m = self.pair_margin(x, i, j, xp)
            margin = m if margin is None else xp.minimum(margin, m)
        return margin

    # ------------------------------------------------------------------ geometry (envs, rendering)
    def car_poses(self, x: Sequence[Column], xp: Backend) -> list[tuple[Column, Column, Column]]:
        """(x, y, heading) of every car in the world frame."""
        n = len(self.cars)
        return [(x[2 * i], x[2 * i + 1], x[2 * n + i]) for i in range(n)]

    @property
    def car_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cars)

    @property
    def car_roles(self) -> tuple[str, ...]:
        return tuple(c.role for c in self.cars)

    @property
    def car_max_turn_rates(self) -> tuple[float, ...]:
        return tuple(c.max_turn_rate for c in self.cars)


class UniformCars(MultiVehicle):
    """A multi-vehicle system whose cars share one speed and turn-rate bound: its parameters are
    those two numbers (and the shared radius, horizon and box), not a list of cars."""

    def __init__(
        self,
        cars: Sequence[Car],
        speed: float,
        max_turn_rate: float,
        collision_radius: float,
        horizon: float,
        half_width: float,
    ) -> None:
        super().__init__(list(cars), collision_radius=collision_radius, horizon=horizon, half_width=half_width)
        self._params = {
            "speed": float(speed),
            "max_turn_rate": float(max_turn_rate),
            "collision_radius": float(collision_radius),
            "horizon": float(horizon),
            "half_width": float(half_width),
        }

    def parameters(self) -> dict[str, Any]:
        return dict(self._params)


class MultiVehicle6D(UniformCars):
    """Air3D's pursuit-evasion game in absolute coordinates: car 1 evades (control), car 2 pursues.

    :meth:`relative_coordinates` maps a 6D state to the Air3D state (the pursuer's position and
    heading in the evader's frame), so trajectories of both systems can be compared exactly.
    """

    name = "multivehicle6d"

    def __init__(
        self,
        speed: float = 0.75,
        max_turn_rate: float = 3.0,
        collision_radius: float = 0.25,
        horizon: float = 1.1,
        half_width: float = 1.0,
    ) -> None:
        cars = [Car(speed, max_turn_rate, "control", "evader_1"), Car(speed, max_turn_rate, "disturbance", "pursuer_1")]
        super().__init__(cars, speed, max_turn_rate, collision_radius, horizon, half_width)

    def relative_coordinates(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        """Air3D state ``(x1, x2, x3)`` of 6D columns ``(xe, ye, xp, yp, the, thp)``."""
        xe, ye, xq, yq, the, thq = x
        dx, dy = xq - xe, yq - ye
        c, s = xp.cos(the), xp.sin(the)
        return [c * dx + s * dy, -s * dx + c * dy, xp.wrap_angle(thq - the)]


#: A second 9D slice (ours): cars 2 and 3 head-on across the x axis, car 1 heading east.
SECOND_9D_SLICE = (0.0, 0.0, 0.0, 0.5, 0.0, -0.5, 0.0, -math.pi / 2, math.pi / 2)

#: DeepReach's 9D slice: car 2 at (-0.4, 0), car 3 at (0.4, 0), headings pi/2, pi/4, 3 pi/4; axes x1, y1.
DEEPREACH_9D_SLICE = (0.0, 0.0, -0.4, 0.0, 0.4, 0.0, math.pi / 2, math.pi / 4, 3 * math.pi / 4)

#: The slice of DeepReach's 2021 figure comparing the 9D BRT with the union of pairwise BRTs (its
#: validation script ``2E1P_valfunc_and_BRT.py``, at t = 1.0): car 1 varies over (x1, y1) with heading
#: -2.54, car 2 at (-0.4, 0) heading 0, car 3 at (0.43, 0.33) heading -2.44.
PAPER_2021_9D_SLICE = (0.0, 0.0, -0.4, 0.0, 0.43, 0.33, -2.54, 0.0, -2.44)


class MultiVehicle9D(UniformCars):
    """DeepReach's MultiVehicleCollision: three cooperating cars (all controls), v = 0.6, w_max = 1.1."""

    name = "multivehicle9d"

    def __init__(
        self,
        speed: float = 0.6,
        max_turn_rate: float = 1.1,
        collision_radius: float = 0.25,
        horizon: float = 1.0,
        half_width: float = 1.0,
    ) -> None:
        cars = [Car(speed, max_turn_rate, "control", f"car_{i}") for i in (1, 2, 3)]
        super().__init__(cars, speed, max_turn_rate, collision_radius, horizon, half_width)

    def plot_slices(self) -> list[tuple[tuple[float, ...], tuple[int, int], str]]:
        """DeepReach's slice, the 2021 paper's figure's slice and one of ours, all over car 1's (x, y)."""
        return [
            (DEEPREACH_9D_SLICE, (0, 1), "DeepReach: cars 2, 3 at (-0.4, 0), (0.4, 0)\nheadings pi/2, pi/4, 3pi/4"),
            (
                PAPER_2021_9D_SLICE,
                (0, 1),
                "2021 figure: cars 2, 3 at (-0.4, 0), (0.43, 0.33)\nheadings -2.54, 0, -2.44",
            ),
            (SECOND_9D_SLICE, (0, 1), "cars 2, 3 at (0, 0.5), (0, -0.5) facing each other\ncar 1 heading 0"),
        ]


#: A 12D slice (ours): DeepReach's 9D slice with a fourth car at (0, -0.5) heading north, at car 1's box.
FOUR_CAR_SLICE = (0.0, 0.0, -0.4, 0.0, 0.4, 0.0, 0.0, -0.5, math.pi / 2, math.pi / 4, 3 * math.pi / 4, math.pi / 2)

#: A 15D slice (ours): the 12D slice with a fifth car at (0, 0.55) heading south.
FIVE_CAR_SLICE = (
    0.0, 0.0, -0.4, 0.0, 0.4, 0.0, 0.0, -0.5, 0.0, 0.55,
    math.pi / 2, math.pi / 4, 3 * math.pi / 4, math.pi / 2, -math.pi / 2,
)  # fmt: skip


class CooperatingCars(UniformCars):
    """``num_cars`` identical cooperating cars (all controls) with DeepReach's 9D parameters
    (v = 0.6, w_max = 1.1, R = 0.25, the box [-1, 1]^2 per car): the N-car family that grows
    :class:`MultiVehicle9D` to 12D and 15D. Every pair of cars is a failure pair, so the union of
    pairwise BRTs of one :class:`~reach.systems.RelativePair` bounds the value from above at any N."""

    num_identical_cars = 3
    #: the plot slice of the subclasses: a base state over car 1's (x, y), and its title
    slice_state: tuple[float, ...] = ()
    slice_title = ""

    def __init__(
        self,
        speed: float = 0.6,
        max_turn_rate: float = 1.1,
        collision_radius: float = 0.25,
        horizon: float = 1.0,
        half_width: float = 1.0,
    ) -> None:
        cars = [Car(speed, max_turn_rate, "control", f"car_{i}") for i in range(1, self.num_identical_cars + 1)]
        super().__init__(cars, speed, max_turn_rate, collision_radius, horizon, half_width)

    def plot_slices(self) -> list[tuple[tuple[float, ...], tuple[int, int], str]]:
        """Car 1's (x, y) with the other cars placed around it (``slice_state``, ``slice_title``); the
        domain centre where a fleet declares no slice."""
        if not self.slice_state:
            return super().plot_slices()
        return [(self.slice_state, (0, 1), self.slice_title)]


class MultiVehicle12D(CooperatingCars):
    """Four cooperating cars (12D): DeepReach's three-car system with one more car."""

    name = "multivehicle12d"
    num_identical_cars = 4
    slice_state = FOUR_CAR_SLICE
    slice_title = "cars 2-4 at (-0.4, 0), (0.4, 0), (0, -0.5)\nheadings pi/2, pi/4, 3pi/4, pi/2"


class MultiVehicle15D(CooperatingCars):
    """Five cooperating cars (15D): DeepReach's three-car system with two more cars."""

    name = "multivehicle15d"
    num_identical_cars = 5
    slice_state = FIVE_CAR_SLICE
    slice_title = "cars 2-5 at (-0.4, 0), (0.4, 0), (0, -0.5), (0, 0.55)\nheadings pi/2, pi/4, 3pi/4, pi/2, -pi/2"
