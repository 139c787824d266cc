"""Gymnasium environment for any scene or system: ``Air3D-v0``, ``MultiVehicle6D-v0``,
``MultiVehicle9D-v0``, and ``Reach-v0`` for any system (``gym.make("Reach-v0", system=...)``, the
same as :func:`reach_envs.make_env`).

Actions are the system's controls (the controlled cars' turn rates) normalised to [-1, 1] (values
outside are clipped to the box; NaN, inf and wrong shapes raise ``ValueError``). The disturbance
comes from the scene. Observations are float32 states with periodic dimensions (headings) wrapped to
[-pi, pi). ``render_mode="rgb_array"`` draws cars, or for a system without cars the projection view
(:mod:`reach_envs.projection`). An episode *terminates* on
collision (``l(x) <= 0``, if the scene says so) or on leaving the arena, and is *truncated* at the
horizon. The reward is -1 on a step that ends in collision and 0 otherwise: the env is a safety
testbed, and reward shaping belongs in a wrapper.

Stepping before ``reset`` or after the episode ended raises
:class:`~reach_envs.spaces.EpisodeOverError`, and unknown ``reset`` options raise ``ValueError``.

``info`` holds ``margin`` (``l(x)``), ``collision``, ``out_of_arena``, ``control`` and
``disturbance`` (inputs actually applied, physical units, after clipping) and ``time`` (seconds).

A single step runs on Python floats (see :mod:`reach.systems.arrays`): at one state, array
libraries' per-call overhead would cost more than the arithmetic.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from reach.systems.arrays import FLOAT
from reach_envs.scenes import Scene, env_scene
from reach_envs.simulator import SceneSimulator
from reach_envs.spaces import (
    EpisodeOverError,
    action_space,
    check_action,
    check_reset_options,
    check_state,
    observation_space,
)
from reach_envs.views import make_renderer, render_frame, trail_points


class ReachEnv(gym.Env[np.ndarray, np.ndarray]):
    """A single environment of a :class:`~reach_envs.scenes.Scene`, or of any system.

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
        self._sampler = self.scene.sampler()
        self._dt = self.scene.dt
        self._max_steps = self.scene.max_steps
        self._terminate_on_collision = self.scene.terminate_on_collision
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
        u = [
            c + h * (-1.0 if v < -1.0 else (1.0 if v > 1.0 else v)) for v, c, h in zip(a, self._u_centre, self._u_half)
        ]
        sim = self.sim
        x = self._state
        d = sim.disturbance(x, self.np_random)
        x = self._state = sim.advance(x, u, d, self.np_random)
        self._steps += 1
        self._time = self._steps * self._dt
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
        return np.array(x, dtype=np.float32), (-1.0 if collision else 0.0), terminated, truncated, info

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
