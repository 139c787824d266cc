"""PettingZoo parallel environment for multi-vehicle scenes: one agent per control car.

Each agent acts its own turn rate, normalised to [-1, 1] as a ``(1,)`` action, and observes the full
float32 state. Disturbance cars are driven by the scene's policy. An agent terminates when its car
collides (comes within the collision radius of another live car) if the scene terminates on
collision, or when any car leaves the arena; a crashed car stops where it is and no longer takes
part in collision checks. All remaining agents are truncated at the horizon. Reward: -1 on the step
an agent's car collides, 0 otherwise.

Only avoid problems: a scene of a reach or reach-avoid system raises ``ValueError`` naming its kind
(its goal is the whole system's, not one car's; use :class:`~reach_envs.env.ReachEnv`).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from reach.systems.arrays import FLOAT
from reach.systems.multivehicle import MultiVehicle
from reach_envs.scenes import Scene, make_scene
from reach_envs.simulator import SceneSimulator
from reach_envs.spaces import action_space, check_action, check_reset_options, check_state, observation_space
from reach_envs.views import make_renderer


class MultiVehicleParallelEnv(ParallelEnv):
    """Parallel multi-agent env over a :class:`MultiVehicle` scene (``"three-car-9d"`` by default)."""

    metadata = {"render_modes": ["rgb_array"], "name": "reach_multivehicle_v0", "is_parallelizable": True}

    def __init__(self, scene: str | Scene = "three-car-9d", render_mode: str | None = None, **overrides: Any) -> None:
        self.scene = make_scene(scene, **overrides)
        system = self.system = self.scene.system
        if system.kind != "avoid":  # per-car collision margins and rewards are an avoid game's
            raise ValueError(
                f"MultiVehicleParallelEnv handles avoid problems only (per-car collisions); {system.name} is a "
                f"{system.kind} problem: use ReachEnv (gym.make('Reach-v0', system=...))"
            )
        if not isinstance(system, MultiVehicle):
            raise ValueError(f"MultiVehicleParallelEnv needs a MultiVehicle scene, got system {system.name}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.render_mode = render_mode
        self.sim = SceneSimulator(self.scene, FLOAT)
        self.possible_agents = [system.cars[i].name for i in system.control_cars]
        self.agents: list[str] = []
        self._agent_car = {name: i for i, name in zip(system.control_cars, self.possible_agents)}
        self._agent_input = {name: k for k, name in enumerate(self.possible_agents)}
        self._obs_space = observation_space(system)
        self._act_space = action_space(1)
        self._half = system.control_bounds.half_width
        self._sampler = self.scene.sampler()
        self._record_trails = self.scene.trails and render_mode is not None
        self._rng, _ = seeding.np_random(None)
        self._renderer = None
        self._state: list[float] = []
        self._crashed = [False] * system.num_cars
        self._steps = 0
        self._trails: list[list[tuple[float, float]]] = []

    @functools.cache  # noqa: B019 - PettingZoo's convention: one space object per agent
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Box:
        return self._act_space

    # ------------------------------------------------------------------ helpers
    def _observations(self) -> dict[str, np.ndarray]:
        obs = np.array(self._state, dtype=np.float32)
        return {a: obs.copy() for a in self.agents}

    def _car_margins(self) -> list[float]:
        """Per car, the smallest ``||p_i - p_j|| - R`` over other live cars in a failure pair."""
        margins = [float("inf")] * self.system.num_cars
        for i, j in self.system.failure_pairs:
            if self._crashed[i] or self._crashed[j]:
                continue
            m = self.system.pair_margin(self._state, i, j, FLOAT)
            margins[i] = min(margins[i], m)
            margins[j] = min(margins[j], m)
        return margins

    # ------------------------------------------------------------------ PettingZoo API
    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        if seed is not None:
            self._rng, _ = seeding.np_random(seed)
        options = check_reset_options(options, ("state",), unknown_keys="warn")
        if options.get("state") is not None:
            x = check_state(options["state"], self.system)
        else:
            x = check_state(self._sampler.sample(self.system, self._rng), self.system)
        self._state = self.system.wrap_columns(x.tolist(), FLOAT)
        self.agents = list(self.possible_agents)
        self._crashed = [False] * self.system.num_cars
        self._steps = 0
        if self._record_trails:
            self._trails = [[(px, py)] for px, py, _ in self.system.car_poses(self._state, FLOAT)]
        margins = self._car_margins()
        infos = {
            a: {"margin": margins[self._agent_car[a]], "collision": margins[self._agent_car[a]] <= 0.0, "time": 0.0}
            for a in self.agents
        }
        return self._observations(), infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        missing = [a for a in self.agents if a not in actions]
        unknown = [a for a in actions if a not in self.agents]
        if missing or unknown:
            raise ValueError(
                f"actions must have one entry per live agent {self.agents}; missing {missing}, unknown {unknown}"
            )
        u = [0.0] * self.system.control_dim
        for agent in self.agents:
            v = float(check_action(actions[agent], (1,))[0])
            k = self._agent_input[agent]
            u[k] = self._half[k] * (-1.0 if v < -1.0 else (1.0 if v > 1.0 else v))
        previous = self._state
        d = self.sim.disturbance(previous, self._rng)
        x = self.sim.advance(previous, u, d, self._rng)
        n = self.system.num_cars
        for i, crashed in enumerate(self._crashed):
            if crashed:  # a crashed car stays where it stopped
                x[2 * i], x[2 * i + 1], x[2 * n + i] = previous[2 * i], previous[2 * i + 1], previous[2 * n + i]
        self._state = x
        self._steps += 1
        time = self._steps * self.scene.dt
        margins = self._car_margins()
        hit = [m <= 0.0 for m in margins]
        out = bool(self.sim.out_of_arena(x))
        truncate = self._steps >= self.scene.max_steps
        rewards, terminations, truncations, infos = {}, {}, {}, {}
        for agent in self.agents:
            car = self._agent_car[agent]
            collided = hit[car]
            rewards[agent] = -1.0 if collided else 0.0
            terminations[agent] = (collided and self.scene.terminate_on_collision) or out
            truncations[agent] = truncate and not terminations[agent]
            infos[agent] = {
                "margin": margins[car],
                "collision": collided,
                "out_of_arena": out,
                "control": u[self._agent_input[agent]],
                "time": time,
            }
        if self.scene.terminate_on_collision:
            for i, collided in enumerate(hit):
                self._crashed[i] = self._crashed[i] or collided
        if self._record_trails:
            for i, (trail, (px, py, _)) in enumerate(zip(self._trails, self.system.car_poses(x, FLOAT))):
                if not self._crashed[i] or trail[-1] != (px, py):
                    trail.append((px, py))
        observations = self._observations()
        self.agents = [a for a in self.agents if not (terminations[a] or truncations[a])]
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        if self._renderer is None:
            self._renderer = make_renderer(self.scene)
        poses = self.system.car_poses(self._state, FLOAT)
        trails = self._trails if self._record_trails else None
        return self._renderer.render(poses, self._steps * self.scene.dt, trails, self._crashed)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def state(self) -> np.ndarray:
        """The global state (float32), as PettingZoo's ``state()`` API expects."""
        return np.array(self._state, dtype=np.float32)

    @property
    def full_state(self) -> np.ndarray:
        """The global state in float64 (``state()`` is its float32 copy, as PettingZoo expects)."""
        return np.array(self._state)

    @property
    def elapsed(self) -> float:
        """Seconds since the last reset."""
        return self._steps * self.scene.dt

    def control_index(self, agent: str) -> int:
        """The index of ``agent``'s turn rate in the system's control vector."""
        if agent not in self._agent_input:
            raise ValueError(f"unknown agent {agent!r}; agents are {self.possible_agents}")
        return self._agent_input[agent]

    @property
    def state_space(self) -> spaces.Box:
        return self._obs_space


def parallel_env(
    scene: str | Scene = "three-car-9d", render_mode: str | None = None, **overrides: Any
) -> MultiVehicleParallelEnv:
    """PettingZoo-style constructor: ``reach_envs.parallel.parallel_env("head-on")``."""
    return MultiVehicleParallelEnv(scene, render_mode=render_mode, **overrides)
