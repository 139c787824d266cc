"""Gymnasium environment for any scene or system: ``Air3D-v0``, ``MultiVehicle6D-v0``,
``MultiVehicle9D-v0``, and ``Reach-v0`` for any system (``gym.make("Reach-v0", system=...)``, the
same as :func:`reach_envs.make_env`).

Actions are the system's controls (the controlled cars' turn rates) normalised to [-1, 1] (values
outside are clipped to the box; NaN, inf and wrong shapes raise ``ValueError``). The disturbance
comes from the scene. Observations are float32 states with periodic dimensions (headings) wrapped to
[-pi, pi). ``render_mode="rgb_array"`` draws cars, or for a system without cars (or of a reach
kind) the projection view (:mod:`reach_envs.projection`), the goal green, obstacles and failure sets
red. What ends an episode and what it earns follow the system's kind (:mod:`reach.systems.problem`,
:mod:`reach_envs.regions`); states are judged after each step:

=============  =======================================  ==========================================  ==========
kind           *terminates* on                          reward of a step                            outcome
=============  =======================================  ==========================================  ==========
avoid          collision ``l(x) <= 0`` (if the scene    -1 if it ends in collision (terminating or  (no key)
               says so), leaving the arena              not), else 0
reach          goal ``l(x) <= 0``, leaving the arena    +1 on reaching the goal, else 0             reached,
                                                                                                    out_of_arena,
                                                                                                    timeout
reach-avoid    collision ``g(x) <= 0`` (even inside     +1 on reaching the goal, -1 on collision,   reached,
               the goal), goal ``l(x) <= 0``,           else 0                                      collided,
               leaving the arena                                                                    out_of_arena,
                                                                                                    timeout
=============  =======================================  ==========================================  ==========

Every kind is *truncated* at the horizon; for a reach kind that is a failure, ``outcome="timeout"``
(reward 0). No kind shapes its reward: the env is a testbed of the reachability problem, and shaping
(distance to the goal, say) belongs in a wrapper.

Stepping before ``reset`` or after the episode ended raises
:class:`~reach_envs.spaces.EpisodeOverError`, and unknown ``reset`` options raise ``ValueError``.

``info`` holds ``margin`` (avoid: the failure margin ``l(x)``; reach kinds: the constraint margin
``g(x)``, ``+inf`` for reach, which has no obstacle), ``collision``, ``out_of_arena``, ``control`` and
``disturbance`` (inputs actually applied, physical units, after clipping) and ``time`` (seconds). A
reach kind adds ``target_margin`` (``l(x)``), ``constraint_margin`` (``g(x)``), ``reached`` (in the
goal and no obstacle) and ``outcome``: ``"reached"``, ``"collided"``, ``"out_of_arena"`` or
``"timeout"`` on the step that ends the episode, ``None`` before (and at ``reset``). A NaN or
infinite margin or state raises ``ValueError`` naming the state, for every kind (fail closed).

A single step runs on Python floats (see :mod:`reach.systems.arrays`): at one state, array
libraries' per-call overhead would cost more than the arithmetic.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from reach.systems.arrays import FLOAT
from reach.systems.box import Ball
from reach_envs.regions import OUTCOME_REWARDS, episode_outcome
from reach_envs.scenes import Scene, env_scene
from reach_envs.simulator import SceneSimulator
from reach_envs.spaces import (
    EpisodeOverError,
    action_space,
    check_action,
    check_reset_options,
    check_state,
    inputs_of_actions,
    observation_space,
)
from reach_envs.views import make_renderer, render_frame, trail_points


class ReachEnv(gym.Env[np.ndarray, np.ndarray]):
    """A single environment of a :class:`~reach_envs.scenes.Scene`, or of any system.

    Rewards by the system's kind (see the module docstring for termination and ``info``):

    =============  ==================  ================  ==================================
    kind           collision step      goal reached      any other step (timeout included)
    =============  ==================  ================  ==================================
    avoid          -1                  (no goal)         0
    reach          (no obstacle)       +1, terminates    0
    reach-avoid    -1, terminates      +1, terminates    0
    =============  ==================  ================  ==================================

    Args:
        scene: a :class:`Scene` or a named scene (``"air3d"``, ``"head-on"``, ...).
        render_mode: ``None`` or ``"rgb_array"``.
        system: instead of ``scene``, any system: an instance, a registered name or an import path
            ``"pkg.mod:Class"`` (:func:`~reach_envs.scenes.system_scene`). Exactly one of ``scene``
            and ``system`` must be given (``ValueError`` otherwise).
        **overrides: scene fields to set, e.g. ``dt=0.01, integrator="euler", disturbance="random"``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(
        self, scene: str | Scene | None = None, render_mode: str | None = None, *, system: Any = None, **overrides: Any
    ) -> None:
        self.scene = env_scene(scene, system, **overrides)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / self.scene.dt))}
        system = self.system = self.scene.system
        self.sim = SceneSimulator(self.scene, FLOAT)
        self.observation_space = observation_space(system)
        self.action_space = action_space(system.control_dim)
        self._action_shape = (system.control_dim,)
        self._u_centre = system.control_bounds.center
        self._u_half = system.control_bounds.half_width
        self._u_ball = isinstance(system.control_bounds, Ball)
        self._sampler = self.scene.sampler()
        self._dt = self.scene.dt
        self._max_steps = self.scene.max_steps
        self._terminate_on_collision = self.scene.terminate_on_collision
        self._reaches = system.problem.reaches
        self._record_trails = self.scene.trails and render_mode is not None
        self._trail_points = trail_points(self.scene) if self._record_trails else None
        self._renderer = None
        self._state: list[float] = []
        self._time = 0.0
        self._steps = 0
        self._trails: list[list[tuple[float, float]]] = []
        self._crashed = False
        #: why step() is refused (before the first reset, after the episode ended), else None
        self._over: str | None = "before reset()"

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode; ``options={"state": x}`` starts from a given state instead of sampling."""
        options = check_reset_options(options, ("state",))
        super().reset(seed=seed)
        if options.get("state") is not None:
            x = check_state(options["state"], self.system)
        else:
            x = check_state(self._sampler.sample(self.system, self.np_random), self.system)
        self._state = self.system.wrap_columns(x.tolist(), FLOAT)
        self._time = 0.0
        self._steps = 0
        self._crashed = False
        self._over = None
        if self._record_trails:
            self._trails = [[p] for p in self._trail_points(self._state)]
        if self._reaches:
            target, constraint, collision, reached = self.sim.reach_status(self._state)
            info = {"margin": constraint, "collision": bool(collision), "time": 0.0}
            info.update(target_margin=target, constraint_margin=constraint, reached=bool(reached), outcome=None)
        else:
            margin = self.sim.margin(self._state)
            info = {"margin": margin, "collision": margin <= 0.0, "time": 0.0}
        return np.array(self._state, dtype=np.float32), info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._over is not None:
            raise EpisodeOverError(
                f"step() called {self._over}; call reset() to start an episode (simulating on would run "
                "inside the failure set or past the horizon)"
            )
        a = check_action(action, self._action_shape).tolist()
        if self._u_ball:
            u = inputs_of_actions(np.asarray(a), self.system.control_bounds).tolist()
        else:  # per-input clip in Python floats: the fast path of one env step
            u = [
                c + h * (-1.0 if v < -1.0 else (1.0 if v > 1.0 else v))
                for v, c, h in zip(a, self._u_centre, self._u_half)
            ]
        sim = self.sim
        x = self._state
        d = sim.disturbance(x, self.np_random)
        x = self._state = sim.advance(x, u, d, self.np_random)
        self._steps += 1
        self._time = self._steps * self._dt
        if self._reaches:
            target, margin, collision, reached = sim.reach_status(x)
            collision, reached = bool(collision), bool(reached)
            out = sim.out_of_arena(x)
            terminated = bool(collision or reached or out)
        else:
            margin = sim.margin(x)
            collision = margin <= 0.0
            out = sim.out_of_arena(x)
            terminated = bool((collision and self._terminate_on_collision) or out)
        truncated = not terminated and self._steps >= self._max_steps
        if terminated or truncated:
            self._over = "after the episode was " + ("terminated" if terminated else "truncated")
        self._crashed = collision
        if self._record_trails:
            for trail, p in zip(self._trails, self._trail_points(x)):
                trail.append(p)
        info = {
            "margin": margin,
            "collision": collision,
            "out_of_arena": bool(out),
            "control": np.array(u),
            "disturbance": np.array(d),
            "time": self._time,
        }
        if not self._reaches:
            return np.array(x, dtype=np.float32), (-1.0 if collision else 0.0), terminated, truncated, info
        outcome = episode_outcome(collision, reached, bool(out), truncated)
        info.update(target_margin=target, constraint_margin=margin, reached=reached, outcome=outcome)
        reward = OUTCOME_REWARDS[outcome] if outcome is not None else 0.0
        return np.array(x, dtype=np.float32), reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array' to gym.make")
            return None
        if self._renderer is None:
            self._renderer = make_renderer(self.scene)
        trails = self._trails if self._record_trails else None
        return render_frame(self._renderer, self.system, self._state, self._time, trails, self._crashed)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # ------------------------------------------------------------------ extras
    @property
    def state(self) -> np.ndarray:
        """The current state in float64 (observations are its float32 copy)."""
        return np.array(self._state)

    @property
    def time(self) -> float:
        """Elapsed time in the episode (seconds)."""
        return self._time
