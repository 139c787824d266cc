"""Fleet scenes: where N constant-speed Dubins cars start and where each one is going.

A fleet state is a float64 torch tensor ``x`` of shape ``(B, 3N)`` in
:class:`~reach.systems.multivehicle.MultiVehicle` order ``(x1, y1, ..., xN, yN, th1, ..., thN)``, and
each car's goal a point, ``goals`` of shape ``(B, N, 2)``. A :class:`FleetScene` fixes the cars (speed,
turn-rate bound, collision radius), the layout and the episode timing; :meth:`FleetScene.sample` draws
a batch of episodes' initial states and goals in one vectorised pass.

Layouts (each for any N >= 2; the tests cover 2 to 64):

``"circle-swap"``
    The cars evenly spaced on a circle, each heading for the centre, each car's goal its antipode: with
    no avoidance every car meets every other at the centre. The radius grows with N so that neighbours
    start at least ``separation`` apart (at least two separations for small N, so a pair has room to
    react). Each episode jitters every start by up to ``jitter`` in each coordinate and every heading by
    up to ``jitter`` radians; the goal is the antipode of the jittered start.
``"random-goals"``
    A square arena of side ``sqrt(N / density)`` (``density`` cars per unit area). Starts and goals are
    uniform in it, starts pairwise at least ``separation`` apart, goals likewise, and each goal at least
    ``separation`` from its own car's start; headings uniform. The draw is a vectorised rejection: each
    round redraws every point too close to a lower-numbered one. A density whose packing (discs of
    diameter ``separation``) is beyond what random sequential placement can reach is refused on
    construction with a ``ValueError`` naming it; a draw that still fails raises one too.
``"intersection"``
    A four-way crossing at the origin, arms east, north, west and south. Cars are dealt round-robin
    to the arms and queued along them, ``separation`` apart from ``2 separation`` out, each heading
    in, in the lane one collision radius to the right of its arm's centre line (opposing lanes two
    radii apart). Per episode each arm's queue is shifted out by a uniform draw of up to one
    separation, so crossing traffic reaches the conflict points at random relative times.
    ``exits="straight"``: each car's goal lies straight across, in the outbound lane at its own
    queue distance; ``exits="random"``: per episode, the (up to) four cars of each queue rank exit
    by a random derangement of the arms (no car turns back), so each car may go right, straight or
    left while every exit lane still receives one car per rank and no two goals coincide. Starts are
    jittered along the arm.

The default horizon (``horizon=None``) is twice the time the slowest car takes to drive the layout's
longest start-to-goal line, plus the time of one full turn at the smallest turn-rate bound: an
unhindered goal-seeking car arrives well within it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from reach.systems.multivehicle import Car, MultiVehicle
from reach.validation import check_float, check_int, check_seed, positive_finite

LAYOUTS = ("circle-swap", "random-goals", "intersection")
EXITS = ("straight", "random")
MAX_CARS = 1024
#: the highest packing fraction (area of discs of diameter ``separation`` over the arena's) that
#: ``random-goals`` accepts; random sequential placement of discs jams near 0.547
MAX_PACKING = 0.4
#: rejection rounds before a ``random-goals`` draw gives up
MAX_ROUNDS = 2000
#: the exits of the four arms (east, north, west, south) that send no car back up its own arm
DERANGEMENTS = np.array([p for p in itertools.permutations(range(4)) if all(p[a] != a for a in range(4))])


def _per_car(name: str, value: Any, n: int) -> tuple[float, ...]:
    """One positive finite float per car, from a number (shared) or a sequence of ``n``."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (Sequence, np.ndarray)):
        return (positive_finite(name, value),) * n
    if len(value) != n:
        raise ValueError(f"FleetScene: {name} must be a number or {n} numbers (one per car), got {len(value)}")
    return tuple(positive_finite(f"{name}[{i}]", v) for i, v in enumerate(value))


@dataclass(frozen=True)
class FleetScene:
    """A fleet of N cars, the layout they start in and the timing of an episode (see the module docstring).

    Attributes:
        layout: one of :data:`LAYOUTS`.
        n_cars: N, the number of cars (2 to :data:`MAX_CARS`).
        speed: every car's constant speed, or a tuple of N speeds.
        max_turn_rate: every car's turn-rate bound ``|w_i| <= max_turn_rate``, or a tuple of N.
        collision_radius: two cars collide when their centres are this close.
        goal_radius: a car arrives (and leaves the scene) within this distance of its goal.
        dt: the simulation step (seconds).
        horizon: the episode length (seconds); ``None``: the layout's default (module docstring).
        density: cars per unit area of the ``"random-goals"`` arena.
        separation: the least distance between starts (and between goals); ``None``: 4 collision radii.
        jitter: per-episode jitter of starts (distance) and of circle-swap headings (radians).
        exits: ``"straight"`` or ``"random"``, the intersection's exits.
        seed: the seed :meth:`sample` uses when it is given no generator (``None``: fresh entropy).
    """

    layout: str = "circle-swap"
    n_cars: int = 16
    speed: float | tuple[float, ...] = 0.6
    max_turn_rate: float | tuple[float, ...] = 1.1
    collision_radius: float = 0.25
    goal_radius: float = 0.2
    dt: float = 0.05
    horizon: float | None = None
    density: float = 0.1
    separation: float | None = None
    jitter: float = 0.05
    exits: str = "straight"
    seed: int | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.layout, str) or self.layout not in LAYOUTS:
            raise ValueError(f"FleetScene: layout must be one of {LAYOUTS}, got {self.layout!r}")
        n = check_int("FleetScene: n_cars", self.n_cars, 2, MAX_CARS)
        object.__setattr__(self, "n_cars", n)
        for field in ("speed", "max_turn_rate"):
            value = getattr(self, field)
            per_car = _per_car(field, value, n)
            object.__setattr__(self, field, per_car if isinstance(value, (Sequence, np.ndarray)) else per_car[0])
        for field in ("collision_radius", "goal_radius", "dt", "density"):
            object.__setattr__(self, field, positive_finite(f"FleetScene: {field}", getattr(self, field)))
        if self.horizon is not None:
            horizon = positive_finite("FleetScene: horizon", self.horizon)
            if horizon < self.dt:
                raise ValueError(f"FleetScene: horizon must be at least dt = {self.dt:g}, got {horizon!r}")
            object.__setattr__(self, "horizon", horizon)
        if self.separation is not None:
            sep = check_float("FleetScene: separation", self.separation, low=self.collision_radius, low_open=True)
            object.__setattr__(self, "separation", sep)
        jitter = check_float("FleetScene: jitter", self.jitter, low=0.0, high=self.min_separation / 8)
        object.__setattr__(self, "jitter", jitter)
        if not isinstance(self.exits, str) or self.exits not in EXITS:
            raise ValueError(f"FleetScene: exits must be one of {EXITS}, got {self.exits!r}")
        if self.seed is not None:
            object.__setattr__(self, "seed", check_seed("FleetScene: seed", self.seed))
        if self.layout == "random-goals":
            packing = self.density * math.pi * self.min_separation**2 / 4
            if packing > MAX_PACKING:
                most = MAX_PACKING * 4 / (math.pi * self.min_separation**2)
                raise ValueError(
                    f"FleetScene: density {self.density:g} cars per unit area cannot be met with starts "
                    f"{self.min_separation:g} apart (packing {packing:.2f} > {MAX_PACKING}); at most {most:.3g}"
                )

    # ------------------------------------------------------------------ derived
    @property
    def speeds(self) -> tuple[float, ...]:
        """Each car's speed."""
        return _per_car("speed", self.speed, self.n_cars)

    @property
    def max_turn_rates(self) -> tuple[float, ...]:
        """Each car's turn-rate bound."""
        return _per_car("max_turn_rate", self.max_turn_rate, self.n_cars)

    @property
    def min_separation(self) -> float:
        """``separation``, or its default of 4 collision radii."""
        return self.separation if self.separation is not None else 4.0 * self.collision_radius

    @property
    def circle_radius(self) -> float:
        """The circle swap's radius: neighbours ``separation`` (plus jitter room) apart, at least 2 separations."""
        chord = self.min_separation + 3.0 * self.jitter
        return max(2.0 * self.min_separation, chord / (2.0 * math.sin(math.pi / self.n_cars)))

    @property
    def arena_side(self) -> float:
        """The side of the random-goals arena: ``sqrt(N / density)``."""
        return math.sqrt(self.n_cars / self.density)

    @property
    def queue_length(self) -> int:
        """The intersection: the most cars on one arm."""
        return math.ceil(self.n_cars / 4)

    def _goal_reach(self) -> float:
        """The intersection: the farthest start or goal from the centre (goals mirror the queues)."""
        return 2.0 * self.min_separation + self.queue_length * self.min_separation + self.jitter

    @property
    def max_distance(self) -> float:
        """The longest start-to-goal straight line the layout can draw."""
        if self.layout == "circle-swap":
            return 2.0 * self.circle_radius + 2.0 * math.sqrt(2.0) * self.jitter
        if self.layout == "random-goals":
            return math.sqrt(2.0) * self.arena_side
        return 2.0 * self._goal_reach() + 2.0 * self.collision_radius

    @property
    def extent(self) -> float:
        """Half the side of a square about the origin holding every start and goal (a view's frame)."""
        if self.layout == "circle-swap":
            reach = self.circle_radius + self.jitter
        elif self.layout == "random-goals":
            reach = self.arena_side / 2
        else:
            reach = self._goal_reach()
        return reach + 2.0 * self.collision_radius

    @property
    def episode_horizon(self) -> float:
        """``horizon``, or the layout's default (module docstring)."""
        if self.horizon is not None:
            return self.horizon
        return 2.0 * self.max_distance / min(self.speeds) + 2.0 * math.pi / min(self.max_turn_rates)

    @property
    def max_steps(self) -> int:
        """Steps of ``dt`` in an episode."""
        return max(1, math.ceil(self.episode_horizon / self.dt - 1e-9))

    def system(self) -> MultiVehicle:
        """The fleet as a :class:`~reach.systems.multivehicle.MultiVehicle` (all cars controls): its
        dynamics are the ones the simulator steps."""
        cars = [Car(v, w, "control", f"car_{i + 1}") for i, (v, w) in enumerate(zip(self.speeds, self.max_turn_rates))]
        return MultiVehicle(cars, collision_radius=self.collision_radius, half_width=self.extent)

    # ------------------------------------------------------------------ sampling
    def sample(self, batch: int, rng: np.random.Generator | int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``batch`` episodes: initial states ``(B, 3N)`` and goals ``(B, N, 2)``, float64 torch on the CPU.

        ``rng`` is a NumPy generator, a seed, or ``None`` (the scene's ``seed``); the same seed gives
        the same episodes."""
        b = check_int("FleetScene.sample: batch", batch, 1)
        gen = _generator(rng if rng is not None else self.seed)
        if self.layout == "circle-swap":
            pos, heading, goals = self._circle(b, gen)
        elif self.layout == "random-goals":
            pos, heading, goals = self._random(b, gen)
        else:
            pos, heading, goals = self._intersection(b, gen)
        x = np.concatenate([pos.reshape(b, -1), _wrap(heading)], axis=1)
        return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64)), torch.from_numpy(goals.astype(np.float64))

    def _circle(self, b: int, gen: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, r, j = self.n_cars, self.circle_radius, self.jitter
        angle = 2.0 * math.pi * np.arange(n) / n
        pos = r * np.stack([np.cos(angle), np.sin(angle)], axis=-1)[None] + gen.uniform(-j, j, (b, n, 2))
        heading = np.arctan2(-pos[..., 1], -pos[..., 0]) + gen.uniform(-j, j, (b, n))
        return pos, heading, -pos

    def _random(self, b: int, gen: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, half, sep = self.n_cars, self.arena_side / 2, self.min_separation
        starts = _separated(gen.uniform(-half, half, (b, n, 2)), None, sep, half, gen, self.density)
        goals = _separated(gen.uniform(-half, half, (b, n, 2)), starts, sep, half, gen, self.density)
        return starts, gen.uniform(-math.pi, math.pi, (b, n)), goals

    def _intersection(self, b: int, gen: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, sep, lane = self.n_cars, self.min_separation, self.collision_radius
        k = np.arange(n)
        arm, queue = k % 4, k // 4
        out = np.stack([np.cos(arm * math.pi / 2), np.sin(arm * math.pi / 2)], axis=-1)  # arm direction (N, 2)
        right_in = np.stack([-out[:, 1], out[:, 0]], axis=-1)  # right of the inbound direction -out
        stagger = gen.uniform(0.0, sep, (b, 4))[:, arm]  # each arm's queue shifted out by up to one separation
        dist = 2.0 * sep + queue * sep + stagger + gen.uniform(-self.jitter, self.jitter, (b, n))
        pos = dist[..., None] * out[None] + lane * right_in[None]
        heading = np.broadcast_to(arm * math.pi / 2 + math.pi, (b, n)).copy()
        if self.exits == "straight":
            exit_arm = np.broadcast_to((arm + 2) % 4, (b, n))
        else:  # the four cars of each queue rank exit by a random derangement of the arms: distinct goals
            pick = gen.integers(0, len(DERANGEMENTS), (b, self.queue_length))
            exit_arm = DERANGEMENTS[pick[:, queue], arm[None]]
        goal_dist = np.broadcast_to(2.0 * sep + queue * sep, (b, n))
        e = np.stack([np.cos(exit_arm * math.pi / 2), np.sin(exit_arm * math.pi / 2)], axis=-1)  # (B, N, 2)
        right_out = np.stack([e[..., 1], -e[..., 0]], axis=-1)
        goals = goal_dist[..., None] * e + lane * right_out
        return pos, heading, goals


def _generator(rng: np.random.Generator | int | None) -> np.random.Generator:
    """A NumPy generator from a generator, a seed or ``None``."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        return np.random.default_rng()
    return np.random.default_rng(check_seed("FleetScene.sample: rng", rng))


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles into ``[-pi, pi)``."""
    return np.remainder(angle + math.pi, 2.0 * math.pi) - math.pi


def _separated(
    points: np.ndarray,
    anchors: np.ndarray | None,
    sep: float,
    half: float,
    gen: np.random.Generator,
    density: float,
) -> np.ndarray:
    """``points`` (B, N, 2) redrawn in the square ``[-half, half]^2`` until each is at least ``sep`` from
    every lower-numbered point of its episode (and from its own anchor, if given). Every round redraws
    all offending points at once; a point with no offence never moves again, so the loop ends once the
    density allows it, and raises ``ValueError`` after :data:`MAX_ROUNDS` rounds otherwise."""
    n = points.shape[1]
    lower = np.tril(np.ones((n, n), dtype=bool), k=-1)  # j < i
    for _ in range(MAX_ROUNDS):
        diff = points[:, :, None, :] - points[:, None, :, :]
        close = (np.einsum("bijk,bijk->bij", diff, diff) < sep * sep) & lower
        bad = close.any(axis=2)
        if anchors is not None:
            bad |= np.sum((points - anchors) ** 2, axis=-1) < sep * sep
        count = int(bad.sum())
        if count == 0:
            return points
        points[bad] = gen.uniform(-half, half, (count, 2))
    raise ValueError(
        f"FleetScene: random-goals could not place {n} cars {sep:g} apart at density {density:g} "
        f"in {MAX_ROUNDS} rounds; lower the density or the separation"
    )
