"""DeepReach's public-release systems, restated as control-affine systems with box or ball inputs.

Restated from the physics of DeepReach's ``dynamics/dynamics.py`` (branch ``public_release``,
commit ``2c3bf67``); each class declares physics only, and the Hamiltonian and optimal inputs are
derived by :class:`~reach.systems.base.ControlAffineSystem`. Domains are DeepReach's
``state_test_range``, horizons its default ``tMax`` of 1 s, and ``deepreach`` its state mean and
variance. DeepReach's constructors take their arguments from the command line with no defaults;
the defaults here are ours and are said so where they appear.

* :class:`NarrowPassage`: two kinematic bicycles (10D) that pass a stranded car between two curbs,
  each reaching its goal (reach-avoid) or only avoiding a collision (``avoid_only=True``).
* :class:`Quadrotor`: a 13D quadrotor (position, unit quaternion, velocity, body rates) driven by
  four motor thrusts, avoiding (or reaching) a ball at the origin.
* :class:`ParameterizedVertDrone2D`: a vertical drone whose input gain ``k`` is part of the state,
  avoiding the floor and the ceiling.

* :class:`RocketLanding` and :class:`ReachAvoidRocketLanding`: a planar rocket (6D) whose thrust
  lies in a disc (a :class:`~reach.systems.box.Ball` of inputs), landing (reach), or landing past a
  wall and above the floor (reach-avoid).

Not restated: ``Dubins4D`` defines no dynamics (its ``dsdt`` and ``hamiltonian`` raise
``NotImplementedError``). Every system here declares DeepReach's
``diff_model`` normalisation (``V = b(x) + scale * o``), so a checkpoint of DeepReach's public
release imports (:func:`training.deepreach.load_deepreach`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from reach.systems.arrays import TORCH, Backend, Column, InputMatrix
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Ball, Box
from reach.systems.deepreach_normalisation import DeepReachNormalisation
from reach.systems.dubins import SET_MODES  # DeepReach's set_mode values, one table for every system
from reach.validation import positive_finite


def _maximum(a: Column, b: Column, xp: Backend) -> Column:
    return -xp.minimum(-a, -b)


def _admissible(
    value: Column, floor: float, ceiling: float, low: float, high: float, xp: Backend
) -> tuple[Column, Column]:
    """Centre and half-width of ``[low if value > floor else 0, high if value < ceiling else 0]``:
    an input that may no longer push ``value`` past ``floor`` or ``ceiling``."""
    zero = 0.0 * value
    lo = xp.where(value > floor, zero + low, zero)
    hi = xp.where(value < ceiling, zero + high, zero)
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


class NarrowPassage(ControlAffineSystem):
    """Two kinematic bicycles of wheelbase ``L = 2`` pass a stranded car at (0, -1.8) between curbs at
    ``y = -2.8`` and ``y = 2.8``; car 1 heads for (6, -1.4), car 2 for (-6, 1.4).

    State ``(x, y, heading, v, phi)`` per car, ``x' = v cos(heading)``, ``y' = v sin(heading)``,
    ``heading' = v tan(phi) / L``, ``v' = a``, ``phi' = psi``, with ``a`` in [-4, 2] and ``psi`` in
    [-3 pi, 3 pi]. As in DeepReach, an input may not push ``v`` below 0.001 or above 6.5, nor ``phi``
    beyond ``0.3 pi - 0.001``: there its bound on that side is 0. That box depends on the state, so
    the controls are normalised, ``u`` in [-1, 1]^4 with ``a = centre(x) + half_width(x) u`` (same for
    ``psi``); :meth:`physical_controls` maps them back to ``(a1, psi1, a2, psi2)``. Those limits are
    the system's :meth:`state_limits`: a step that would overshoot one (full throttle from 6.49 held
    for a step) stops at it, as the continuous system does (:mod:`reach.systems.limits`).

    ``g`` (constraint, or failure margin with ``avoid_only``) is ``avoid_fn_weight`` times the least
    of each car's clearance to the curbs (less ``L / 2``), to the stranded car and to the other car
    (less ``L``); the target (reach-avoid only) is both cars within ``L`` of their goals.
    ``avoid_fn_weight`` 1 is ours.
    """

    name = "narrowpassage"
    state_names = ("x1", "y1", "heading1", "v1", "phi1", "x2", "y2", "heading2", "v2", "phi2")
    periodic = (False, False, True, False, False) * 2
    L = 2.0
    goals = ((6.0, -1.4), (-6.0, 1.4))
    speed_limits = (0.001, 6.5)
    steer_limit = 0.3 * math.pi - 0.001
    acceleration = (-4.0, 2.0)
    steer_rate = 3.0 * math.pi
    curbs = (-2.8, 2.8)
    stranded_car = (0.0, -1.8)
    #: the two drivers of a multi-agent env (:mod:`reach_envs.agents`): each acts its car's (a, psi)
    agent_inputs = {"car_1": (0, 1), "car_2": (2, 3)}

    def __init__(self, avoid_fn_weight: float = 1.0, avoid_only: bool = False, horizon: float = 1.0) -> None:
        self.avoid_fn_weight = positive_finite("NarrowPassage: avoid_fn_weight", avoid_fn_weight)
        if not isinstance(avoid_only, bool):
            raise ValueError(f"NarrowPassage: avoid_only must be True or False, got {avoid_only!r}")
        self.avoid_only = avoid_only
        self.kind = "avoid" if avoid_only else "reach-avoid"
        self.horizon = positive_finite("NarrowPassage: horizon", horizon)
        car = ((-8.0, 8.0), (-3.8, 3.8), (-math.pi, math.pi), (-1.0, 7.0), (-0.3 * math.pi, 0.3 * math.pi))
        self.domain = car * 2
        self.control_bounds = Box.symmetric([1.0] * 4)
        self.deepreach = DeepReachNormalisation(
            state_offset=(0.0, 0.0, 0.0, 3.0, 0.0) * 2,
            state_scale=(8.0, 3.8, 1.2 * math.pi, 4.0, 1.2 * 0.3 * math.pi) * 2,
            value_scale=0.5 * 8.0 / 0.02,
            value_offset=0.25 * 8.0,
            model="diff",
        )

    def parameters(self) -> dict[str, Any]:
        return {"avoid_fn_weight": self.avoid_fn_weight, "avoid_only": self.avoid_only, "horizon": self.horizon}

    def _inputs(self, x: Sequence[Column], xp: Backend) -> list[tuple[Column, Column]]:
        """(centre, half-width) of ``a1, psi1, a2, psi2`` at the states ``x``."""
        out = []
        for o in (0, 5):
            out.append(_admissible(x[o + 3], *self.speed_limits, *self.acceleration, xp))
            out.append(
                _admissible(x[o + 4], -self.steer_limit, self.steer_limit, -self.steer_rate, self.steer_rate, xp)
            )
        return out

    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        inputs = self._inputs(x, xp)
        out: list[Column] = []
        for c, o in enumerate((0, 5)):
            heading, v, phi = x[o + 2], x[o + 3], x[o + 4]
            out += [v * xp.cos(heading), v * xp.sin(heading), v * xp.sin(phi) / (xp.cos(phi) * self.L)]
            out += [inputs[2 * c][0], inputs[2 * c + 1][0]]
        return out

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        inputs = self._inputs(x, xp)
        return {(3, 0): inputs[0][1], (4, 1): inputs[1][1], (8, 2): inputs[2][1], (9, 3): inputs[3][1]}

    def state_limits(self) -> dict[int, tuple[float, float]]:
        """Each car's speed within :attr:`speed_limits` and steering angle within ``+-steer_limit``:
        its input bound on a side is 0 at the limit (:meth:`_inputs`), so neither is crossed."""
        steer = (-self.steer_limit, self.steer_limit)
        return {3: self.speed_limits, 4: steer, 8: self.speed_limits, 9: steer}

    def physical_controls(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``(a1, psi1, a2, psi2)`` of normalised controls ``u`` ``(..., 4)`` in [-1, 1] at states ``x``
        ``(..., 10)``; a ``u`` outside [-1, 1] (or NaN) is refused naming it, not mapped past the box."""
        self._check("x", x, self.state_dim)
        self._check("u", u, self.control_dim)
        outside = ~((u >= -1.0) & (u <= 1.0))
        if bool(outside.any()):
            j = int(outside.nonzero()[0, -1])
            value = float(u[outside][0])
            names = ("a1", "psi1", "a2", "psi2")
            raise ValueError(f"NarrowPassage: normalised control u must lie in [-1, 1], got {value!r} for {names[j]}")
        inputs = self._inputs(TORCH.unbind(x), TORCH)
        return torch.stack([c + h * u[..., j] for j, (c, h) in enumerate(inputs)], dim=-1)

    def target_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        if self.avoid_only:
            return super().target_margin_columns(x, xp)  # an avoid problem has no target
        (g1x, g1y), (g2x, g2y) = self.goals
        d1 = xp.hypot(x[0] - g1x, x[1] - g1y) - self.L
        d2 = xp.hypot(x[5] - g2x, x[6] - g2y) - self.L
        return _maximum(d1, d2, xp)

    def constraint_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        if self.avoid_only:
            return super().constraint_margin_columns(x, xp)  # its clearance is the failure margin instead
        return self._clearance(x, xp)

    def failure_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        return self._clearance(x, xp)  # reach-avoid: the constraint margin, as the base class's default

    def travel_bound(self, x: torch.Tensor, time: float) -> tuple[torch.Tensor, torch.Tensor]:
        """How far each car can move within ``time`` seconds from states ``x`` ``(..., 10)``, under any
        admissible inputs: ``|v| time + time^2``.

        Why: a car's speed changes at ``a`` in [-4, 2], and an input may not push it past its limits
        (it starts at most at ``|v|`` and may fall toward 0.001 or below only by its own start), so
        ``|v(s)| <= |v(0)| + 2 s`` and the path is at most ``|v| t + t^2`` long. Held over Euler steps,
        step ``j`` moves the car by ``dt |v_j|`` with ``|v_j| <= |v(0)| + 2 j dt``; an RK4 step by ``dt``
        times a weighted mean of its stages' speeds (positive weights summing to one, stages at most
        ``dt`` later), each at most ``|v(0)| + 2 (j + 1) dt``: summed over the steps, at most the same
        bound. A step that would overshoot a speed limit stops at it, which only shortens the path."""
        t = float(time)
        return x[..., 3].abs() * t + t * t, x[..., 8].abs() * t + t * t

    def target_floor(self, x: torch.Tensor, time: float) -> torch.Tensor | None:
        """``max_i(d_i - L - s_i)`` (reach-avoid): the target margin is the larger of the two cars'
        distances to their goals, less ``L``, and car ``i`` moves no farther than ``s_i``
        (:meth:`travel_bound`), so neither distance can fall by more. ``None`` with ``avoid_only``."""
        if self.avoid_only:
            return None
        s1, s2 = self.travel_bound(x, time)
        (g1x, g1y), (g2x, g2y) = self.goals
        d1 = torch.hypot(x[..., 0] - g1x, x[..., 1] - g1y) - self.L - s1
        d2 = torch.hypot(x[..., 5] - g2x, x[..., 6] - g2y) - self.L - s2
        return torch.maximum(d1, d2)

    def margin_floor(self, x: torch.Tensor, time: float) -> torch.Tensor | None:
        """``g`` with each clearance lowered by how far the cars can move (:meth:`travel_bound`): a
        car's clearance to a curb or to the stranded car by its own ``s_i``, the cars' distance by
        ``s_1 + s_2``; ``avoid_fn_weight`` scales the least of them, as it scales ``g``. A lower bound
        of the constraint margin (the failure margin with ``avoid_only``) under any inputs."""
        return self._clearance(TORCH.unbind(x), TORCH, self.travel_bound(x, time))

    def _clearance(
        self, x: Sequence[Column], xp: Backend, travel: tuple[Column | float, Column | float] = (0.0, 0.0)
    ) -> Column:
        """``g``: the weighted least clearance of the two cars (see the class docstring), each car's
        clearances lowered by how far it may still move (``travel``, per car; none by default) and the
        cars' distance by both."""
        low, high = self.curbs
        sx, sy = self.stranded_car
        s1, s2 = travel
        margin = xp.hypot(x[0] - x[5], x[1] - x[6]) - self.L - (s1 + s2)
        for px, py, s in ((x[0], x[1], s1), (x[5], x[6], s2)):
            margin = xp.minimum(margin, py - low - 0.5 * self.L - s)
            margin = xp.minimum(margin, high - py - 0.5 * self.L - s)
            margin = xp.minimum(margin, xp.hypot(px - sx, py - sy) - self.L - s)
        return self.avoid_fn_weight * margin


class Quadrotor(ControlAffineSystem):
    """DeepReach's 13D quadrotor: position, quaternion ``(qw, qx, qy, qz)``, velocity and body rates,
    driven by four motor thrusts ``u_i`` in ``[-thrust_max, thrust_max]`` (a box, as in DeepReach).

    Mass 1, arm 0.17, thrust coefficient 1, moment coefficient 0.016, gravity 9.8 (DeepReach's fixed
    constants). The total thrust accelerates along the body z axis; the motors' differences turn the
    body. ``set_mode="avoid"`` (DeepReach's only implemented mode) keeps the quadrotor out of the
    ball of radius ``collisionR`` at the origin; ``"reach"`` drives it there. Defaults
    ``collisionR 0.5`` and ``thrust_max 20`` are ours (DeepReach asks for them on its command line).
    """

    name = "quadrotor"
    state_names = ("x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz")
    periodic = (False,) * 13
    mass = 1.0
    arm = 0.17
    thrust_coefficient = 1.0
    moment_coefficient = 0.016
    gravity = 9.8
    #: the sign each motor's thrust takes in the rate equations of wx, wy and wz
    motor_signs = ((1.0, -1.0, 1.0), (-1.0, -1.0, -1.0), (-1.0, 1.0, 1.0), (1.0, 1.0, -1.0))

    def __init__(
        self, collisionR: float = 0.5, thrust_max: float = 20.0, set_mode: str = "avoid", horizon: float = 1.0
    ) -> None:
        if not isinstance(set_mode, str) or set_mode not in SET_MODES:
            raise ValueError(f"Quadrotor: set_mode must be one of {tuple(SET_MODES)}, got {set_mode!r}")
        self.set_mode = set_mode
        self.kind = SET_MODES[set_mode]
        self.collisionR = positive_finite("Quadrotor: collisionR", collisionR)
        self.thrust_max = positive_finite("Quadrotor: thrust_max", thrust_max)
        self.horizon = positive_finite("Quadrotor: horizon", horizon)
        self.domain = ((-1.5, 1.5),) * 3 + ((-1.0, 1.0),) * 4 + ((-10.0, 10.0),) * 6
        self.control_bounds = Box.symmetric([self.thrust_max] * 4)
        reach = math.sqrt(3 * 1.5**2)
        self.deepreach = DeepReachNormalisation(
            state_offset=(0.0,) * 13,
            state_scale=(1.5,) * 3 + (1.0,) * 4 + (10.0,) * 6,
            value_scale=reach / 0.02,
            value_offset=(reach - 2 * self.collisionR) / 2,
            model="diff",
        )

    def parameters(self) -> dict[str, Any]:
        return {
            "collisionR": self.collisionR,
            "thrust_max": self.thrust_max,
            "set_mode": self.set_mode,
            "horizon": self.horizon,
        }

    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        qw, qx, qy, qz, vx, vy, vz, wx, wy, wz = x[3:]
        zero = 0.0 * vx
        return [
            vx,
            vy,
            vz,
            -(wx * qx + wy * qy + wz * qz) / 2.0,
            (wx * qw + wz * qy - wy * qz) / 2.0,
            (wy * qw - wz * qx + wx * qz) / 2.0,
            (wz * qw + wy * qx - wx * qy) / 2.0,
            zero,
            zero,
            zero - self.gravity,
            -5.0 * wy * wz / 9.0,
            5.0 * wx * wz / 9.0,
            zero,
        ]

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        qw, qx, qy, qz = x[3:7]
        k = self.thrust_coefficient / self.mass
        body_z = (
            2.0 * (qw * qy + qx * qz) * k,
            2.0 * (qy * qz - qw * qx) * k,
            (1.0 - 2.0 * qx * qx - 2.0 * qy * qy) * k,
        )
        roll_pitch = 4.0 * math.sqrt(2.0) * self.thrust_coefficient / (3.0 * self.arm * self.mass)
        yaw = 12.0 * self.thrust_coefficient * self.moment_coefficient / (7.0 * self.arm**2 * self.mass)
        matrix: dict[tuple[int, int], Column] = {}
        for j, (sx, sy, sz) in enumerate(self.motor_signs):
            matrix.update({(7, j): body_z[0], (8, j): body_z[1], (9, j): body_z[2]})
            matrix.update({(10, j): sx * roll_pitch, (11, j): sy * roll_pitch, (12, j): sz * yaw})
        return matrix

    def _ball(self, x: Sequence[Column], xp: Backend) -> Column:
        return xp.hypot(xp.hypot(x[0], x[1]), x[2]) - self.collisionR

    def target_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        if self.kind != "reach":
            return super().target_margin_columns(x, xp)  # an avoid problem has no target
        return self._ball(x, xp)

    def failure_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        if self.kind != "avoid":
            return super().failure_margin_columns(x, xp)  # a reach problem has no failure set
        return self._ball(x, xp)


class ParameterizedVertDrone2D(ControlAffineSystem):
    """DeepReach's vertical drone: ``v' = k u - gravity``, ``z' = v``, ``k' = 0``, with ``u`` in
    ``[-input_magnitude_max, input_magnitude_max]`` and the input gain ``k`` a state in
    ``[0, input_multiplier_max]`` (one value function for every gain). It must keep ``z`` within
    [0, 3]: ``l = 1.5 - |z - 1.5|`` (avoid). Defaults ``gravity 9.8``, ``input_multiplier_max 12``
    and ``input_magnitude_max 1`` are ours (DeepReach asks for them on its command line).
    """

    name = "parameterizedvertdrone2d"
    kind = "avoid"
    state_names = ("v", "z", "k")
    periodic = (False, False, False)

    def __init__(
        self,
        gravity: float = 9.8,
        input_multiplier_max: float = 12.0,
        input_magnitude_max: float = 1.0,
        horizon: float = 1.0,
    ) -> None:
        self.gravity = positive_finite("ParameterizedVertDrone2D: gravity", gravity)
        self.input_multiplier_max = positive_finite(
            "ParameterizedVertDrone2D: input_multiplier_max", input_multiplier_max
        )
        self.input_magnitude_max = positive_finite("ParameterizedVertDrone2D: input_magnitude_max", input_magnitude_max)
        self.horizon = positive_finite("ParameterizedVertDrone2D: horizon", horizon)
        self.domain = ((-4.0, 4.0), (-0.5, 3.5), (0.0, self.input_multiplier_max))
        self.control_bounds = Box.symmetric([self.input_magnitude_max])
        half_k = self.input_multiplier_max / 2
        self.deepreach = DeepReachNormalisation(
            state_offset=(0.0, 1.5, half_k), state_scale=(4.0, 2.0, half_k), model="diff"
        )

    def parameters(self) -> dict[str, Any]:
        return {
            "gravity": self.gravity,
            "input_multiplier_max": self.input_multiplier_max,
            "input_magnitude_max": self.input_magnitude_max,
            "horizon": self.horizon,
        }

    def training_domain(self) -> tuple[tuple[float, float], ...]:
        """The domain with its speed range widened down to the fastest fall that still starts above the
        floor: a drone whose gain ``k`` is below ``gravity`` falls whatever it does, and leaves the box
        through ``v = -4`` while still between floor and ceiling (at ``k = 0``, from ``v = 0`` at the
        ceiling, after 0.41 s at height 2.2). Its value comes from where it falls to, outside the box,
        which a residual drawn on the box alone leaves free: a network may call it safe although it
        reaches the floor within the horizon. Thrusting up (``u = 1``, what keeps a falling drone off
        the floor) it falls with at most ``gravity``, so from the box it meets the floor no faster
        than ``min(sqrt(4^2 + 2 gravity 3.5), 4 + gravity horizon)`` downwards (9.2 at the defaults)."""
        (v_low, v_high), (z_low, z_high), gain = self.domain
        fastest_fall = min(math.sqrt(v_low**2 + 2 * self.gravity * z_high), -v_low + self.gravity * self.horizon)
        return ((-fastest_fall, v_high), (z_low, z_high), gain)

    def value_scale(self) -> float:
        """How far the margin can fall within the horizon ``T``: under ``u = min(1, gravity / k)``
        (hover where the gain allows, else full thrust up) the acceleration lies in [-gravity, 0], so
        the height falls by at most ``4 T + gravity T^2 / 2`` and the room to the ceiling by at most
        ``4 T``: ``V >= l - 4 T - gravity T^2 / 2``, which a drone of gain 0 falling at 4 m/s meets."""
        fastest = max(-self.domain[0][0], self.domain[0][1])
        return fastest * self.horizon + 0.5 * self.gravity * self.horizon**2

    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        return [0.0 * x[0] - self.gravity, x[0], 0.0 * x[2]]

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        return {(0, 0): x[2]}

    def failure_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        return 1.5 - xp.abs(x[1] - 1.5)


class RocketLanding(ControlAffineSystem):
    """DeepReach's rocket landing (6D, reach): state ``(x, y, th, vx, vy, w)``, a planar rocket of
    heading ``th`` whose thrust ``u`` lies in a disc of radius 250 (a :class:`Ball` of inputs):
    ``x' = vx``, ``y' = vy``, ``th' = w``, ``vx' = u1 cos th - u2 sin th``,
    ``vy' = u1 sin th + u2 cos th - 9.81``, ``w' = 0.3 u1``. The target is the landing zone
    ``|x| <= 20``, ``y <= 20``, with DeepReach's scaling of the margin: ``m = max(|x| - 20, y - 20)``,
    ``l = m / 150`` outside and ``m / 10`` inside.

    DeepReach's Hamiltonian, ``-250 |(s1, s2)|_2 + p . f``, and its optimal thrust, ``-250 s / |s|``,
    are what the ball's support function derives (``tests/test_deepreach_catalogue.py``).
    """

    name = "rocketlanding"
    kind = "reach"
    state_names = ("x", "y", "th", "vx", "vy", "w")
    periodic = (False, False, True, False, False, False)
    thrust = 250.0
    gravity = 9.81
    torque_arm = 0.3
    landing_half_width = 20.0
    landing_height = 20.0
    #: DeepReach's RocketLanding network takes one more (always zero) input; its reach-avoid twin none
    deepreach_extra_inputs = 1

    def __init__(self, horizon: float = 1.0) -> None:
        self.horizon = positive_finite(f"{type(self).__name__}: horizon", horizon)
        self.domain = (
            (-150.0, 150.0),
            (10.0, 150.0),
            (-math.pi, math.pi),
            (-200.0, 200.0),
            (-200.0, 200.0),
            (-10.0, 10.0),
        )
        self.control_bounds = Ball.centred(2, self.thrust)
        self.deepreach = DeepReachNormalisation(
            state_offset=(0.0, 80.0, 0.0, 0.0, 0.0, 0.0),
            state_scale=(150.0, 70.0, 1.2 * math.pi, 200.0, 200.0, 10.0),
            value_scale=1.0 / 0.02,
            value_offset=0.0,
            model="diff",
            extra_inputs=self.deepreach_extra_inputs,
        )

    def parameters(self) -> dict[str, Any]:
        return {"horizon": self.horizon}

    def drift(self, x: Sequence[Column], xp: Backend) -> list[Column]:
        return [x[3], x[4], x[5], 0.0 * x[3], 0.0 * x[4] - self.gravity, 0.0 * x[5]]

    def control_matrix(self, x: Sequence[Column], xp: Backend) -> InputMatrix:
        c, s = xp.cos(x[2]), xp.sin(x[2])
        return {(3, 0): c, (3, 1): -s, (4, 0): s, (4, 1): c, (5, 0): self.torque_arm}

    def target_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        m = _maximum(xp.abs(x[0]) - self.landing_half_width, x[1] - self.landing_height, xp)
        return xp.where(m >= 0, m / 150.0, m / 10.0)


class ReachAvoidRocketLanding(RocketLanding):
    """:class:`RocketLanding` as a reach-avoid problem (DeepReach's ``ReachAvoidRocketLanding``): land
    without touching the floor ``y = 0`` or a wall, the box ``x`` in [-30, -20], ``y`` in [0, 100].
    ``g = min(y, d_wall)`` with ``d_wall`` the signed distance to the wall (unscaled, as in DeepReach)."""

    name = "reachavoidrocketlanding"
    kind = "reach-avoid"
    deepreach_extra_inputs = 0
    wall = ((-30.0, -20.0), (0.0, 100.0))

    def constraint_margin_columns(self, x: Sequence[Column], xp: Backend) -> Column:
        (left, right), (bottom, top) = self.wall
        dx = _maximum(left - x[0], x[0] - right, xp)
        dy = _maximum(bottom - x[1], x[1] - top, xp)
        outside = xp.hypot(_maximum(dx, 0.0 * dx, xp), _maximum(dy, 0.0 * dy, xp))
        inside = xp.minimum(_maximum(dx, dy, xp), 0.0 * dx)
        return xp.minimum(x[1], outside + inside)


__all__ = ["NarrowPassage", "ParameterizedVertDrone2D", "Quadrotor", "ReachAvoidRocketLanding", "RocketLanding"]
