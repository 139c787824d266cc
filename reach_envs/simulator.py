"""The step of a scene, assembled from its active effects only; shared by every environment kind.

:class:`SceneSimulator` runs on one backend: Python floats for single environments (state = list of
floats) or NumPy for vector environments (state = list of ``(num_envs,)`` columns). At construction
it resolves which effects the scene asks for; the per-step methods then do that work and no other.
The counters in :attr:`SceneSimulator.calls` make this checkable in tests.

Every margin it returns is checked finite: a NaN margin would read as "not in the set" (NaN <= 0 is
False), so it raises ``ValueError`` naming the state instead (fail closed).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from reach.integrators import make_stepper
from reach.systems.arrays import FLOAT, Backend, Column
from reach.systems.box import require_box
from reach_envs.policies import make_disturbance_policy
from reach_envs.scenes import Scene


class SceneSimulator:
    """Advances states of one scene on backend ``xp`` (FLOAT or NUMPY)."""

    def __init__(self, scene: Scene, xp: Backend) -> None:
        self.scene = scene
        self.system = scene.system
        self.xp = xp
        self.calls: Counter[str] = Counter()
        self._step = make_stepper(self.system, scene.dt, scene.integrator, xp)
        self._policy = make_disturbance_policy(self.system, scene.disturbance)
        # disturbance policies clip to (and sample) the box: a ball of disturbances is refused by name
        require_box(self.system.disturbance_bounds, "an env's disturbance policy")
        self._d_low = self.system.disturbance_bounds.low
        self._d_high = self.system.disturbance_bounds.high
        self._d_centre = list(self.system.disturbance_bounds.center)
        noise = None
        if scene.process_noise is not None:
            std = np.broadcast_to(np.asarray(scene.process_noise, dtype=np.float64), (self.system.state_dim,))
            if np.any(std > 0):
                noise = std * math.sqrt(scene.dt)
        self._noise = noise
        self._limited = bool(self.system.state_limits())  # the step keeps them; noise must too
        self._arena = scene.arena
        self._has_constraint = self.system.problem.has_constraint

    # ------------------------------------------------------------------ disturbance
    def disturbance(self, x: Sequence[Column], rng: np.random.Generator) -> list[Column]:
        """The disturbance for this step: the policy's output clipped to the box, else the box centre."""
        if self._policy is None:
            return self._d_centre
        self.calls["disturbance_policy"] += 1
        d = self._policy.columns(x, self.xp, rng)
        return [self.xp.clip(v, lo, hi) for v, lo, hi in zip(d, self._d_low, self._d_high)]

    # ------------------------------------------------------------------ dynamics
    def advance(
        self, x: Sequence[Column], u: Sequence[Column], d: Sequence[Column], rng: np.random.Generator
    ) -> list[Column]:
        """One step of length ``dt``: integrate, add process noise if the scene has any, wrap headings;
        the system's state limits (:mod:`reach.systems.limits`) hold after the noise as after the step.

        A non-finite next state (a user system's drift that returns NaN or overflows) raises
        ``ValueError`` naming the state it came from, instead of returning a NaN observation."""
        before = x
        x = self._step(x, u, d)
        self._require_finite(x, "the next state", before)
        if self._noise is not None:
            self.calls["process_noise"] += 1
            shape = np.shape(x[0])
            z = rng.standard_normal(size=shape + self._noise.shape) * self._noise
            x = [a + b for a, b in zip(x, z.tolist())] if self.xp is FLOAT else [a + z[..., i] for i, a in enumerate(x)]
            x = self.system.wrap_columns(x, self.xp)
            if self._limited:
                x = self.system.saturate_columns(before, x, self.xp)
        return x

    def margin(self, x: Sequence[Column]) -> Column:
        """Failure margin ``l(x)``; a NaN or infinite margin raises ``ValueError`` naming the state
        (it would read as "no collision": NaN <= 0 is False)."""
        value = self.system.failure_margin_columns(x, self.xp)
        self._require_finite([value], "the failure margin", x)
        return value

    def target_margin(self, x: Sequence[Column]) -> Column:
        """Target margin ``l(x)`` of a reach kind (``<= 0`` in the goal); non-finite raises ``ValueError``."""
        value = self.system.target_margin_columns(x, self.xp)
        self._require_finite([value], "the target margin", x)
        return value

    def constraint_margin(self, x: Sequence[Column]) -> Column:
        """Constraint margin ``g(x)`` of a reach-avoid system (``<= 0`` in an obstacle), ``+inf`` for a
        reach system (no obstacle anywhere); non-finite values of ``g`` raise ``ValueError``."""
        if not self._has_constraint:
            return math.inf if self.xp is FLOAT else np.full(np.shape(x[0]), math.inf)
        value = self.system.constraint_margin_columns(x, self.xp)
        self._require_finite([value], "the constraint margin", x)
        return value

    def reach_status(self, x: Sequence[Column]) -> tuple[Column, Column, Column, Column]:
        """For a reach kind: ``(l, g, collision, reached)`` with ``collision = g <= 0`` and ``reached =
        l <= 0 < g`` (a state in the goal and an obstacle is a collision), on floats or arrays alike."""
        target = self.target_margin(x)
        constraint = self.constraint_margin(x)
        collision = constraint <= 0.0
        return target, constraint, collision, (target <= 0.0) & (constraint > 0.0)

    def _require_finite(self, columns: Sequence[Column], what: str, state: Sequence[Column]) -> None:
        """Raise ``ValueError`` if any entry of ``columns`` is NaN or infinite, naming ``state``."""
        if self.xp is FLOAT:
            if all(map(math.isfinite, columns)):
                return
            bad = [float(v) for v in state]
        else:
            finite = np.ones(np.shape(columns[0]), dtype=bool)
            for column in columns:
                finite &= np.isfinite(column)
            if finite.all():
                return
            row = int(np.flatnonzero(~finite)[0])
            bad = [float(np.asarray(v).reshape(-1)[row]) for v in state]
        raise ValueError(f"{self.system.name}: {what} is NaN or infinite at state {bad}; check the system's physics")

    def out_of_arena(self, x: Sequence[Column]) -> Column:
        """Whether any car left the arena (False everywhere when the scene has no arena)."""
        if self._arena is None:
            return False
        self.calls["arena"] += 1
        a = self._arena
        out: Column = False
        for px, py, _ in self.system.car_poses(x, self.xp):
            out = out | (self.xp.abs(px) > a) | (self.xp.abs(py) > a)  # bools and arrays alike
        return out
