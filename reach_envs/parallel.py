"""PettingZoo parallel environment for multi-agent systems: agents are groups of control inputs.

The agents come from :func:`reach_envs.agents.agent_inputs`: one per control car of a
:class:`~reach.systems.multivehicle.MultiVehicle` (its turn rate), ``car_1`` and ``car_2`` of
:class:`~reach.systems.deepreach_catalogue.NarrowPassage` (each car's acceleration and steering
rate), or whatever a system declares in ``agent_inputs``. Each agent acts its inputs normalised to
[-1, 1] as a ``(number of its inputs,)`` action (values outside are clipped) and observes the full
float32 state. Disturbance inputs are driven by the scene's policy.

What ends an agent's episode depends on whose outcome it is:

* **Per car**, for a :class:`MultiVehicle` avoid scene (the car scenes, the N-car family): an agent
  terminates when its car collides (comes within the collision radius of another live car) if the
  scene terminates on collision, or when any car leaves the arena; a crashed car stops where it is
  and no longer takes part in collision checks. Reward: -1 on the step an agent's car collides, else 0.
* **As a team**, for every other system (NarrowPassage, reach and reach-avoid kinds, whose goal is
  the whole system's, not one car's): all agents share the system's outcome and end together, as
  :class:`~reach_envs.env.ReachEnv` ends its one episode. A reach kind terminates every agent on
  reaching the goal (reward +1 each) or on a collision (reward -1 each), and reports
  ``info["outcome"]`` (``"reached"``, ``"collided"``, ``"out_of_arena"``, ``"timeout"``; ``None``
  before) with ``target_margin``, ``constraint_margin`` and ``reached``; an avoid system terminates
  every agent on a collision (if the scene says so), reward -1 each on a collision step.

All remaining agents are truncated at the horizon. ``info`` holds ``margin`` (per car: the car's
closest live pair; as a team: as in :class:`~reach_envs.env.ReachEnv`), ``collision``,
``out_of_arena``, ``control`` (the agent's inputs as applied, physical units: a float for an agent of
one input, else an array) and ``time``. A system without agents raises ``ValueError`` naming it and
its kind (use :class:`~reach_envs.env.ReachEnv`).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from reach.systems.arrays import FLOAT
from reach.systems.box import require_box
from reach.systems.multivehicle import MultiVehicle
from reach_envs.agents import agent_inputs
from reach_envs.regions import OUTCOME_REWARDS, episode_outcome
from reach_envs.scenes import Scene, env_scene
from reach_envs.simulator import SceneSimulator
from reach_envs.spaces import action_space, check_action, check_reset_options, check_state, observation_space
from reach_envs.views import make_renderer, render_frame, trail_points

#: the scene of ``parallel_env()`` without a scene or a system
DEFAULT_SCENE = "three-car-9d"


class MultiVehicleParallelEnv(ParallelEnv):
    """Parallel multi-agent env over a scene of a multi-agent system (``"three-car-9d"`` by default).

    Args:
        scene: a :class:`Scene` or a named scene (``"three-car-9d"``, ``"head-on"``, ``"four-car-12d"``, ...).
        render_mode: ``None`` or ``"rgb_array"``.
        system: instead of ``scene``, a system with agents: an instance, a registered name
            (``"narrowpassage"``) or an import path ``"pkg.mod:Class"``; not both.
        **overrides: scene fields to set, e.g. ``dt=0.01, process_noise=0.02``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "reach_multivehicle_v0", "is_parallelizable": True}

    def __init__(
        self, scene: str | Scene | None = None, render_mode: str | None = None, *, system: Any = None, **overrides: Any
    ) -> None:
        if scene is None and system is None:
            scene = DEFAULT_SCENE
        self.scene = env_scene(scene, system, **overrides)
        system = self.system = self.scene.system
        inputs = agent_inputs(system)
        if inputs is None:
            article = "an" if system.kind == "avoid" else "a"
            raise ValueError(
                f"MultiVehicleParallelEnv needs a multi-agent system (a MultiVehicle, NarrowPassage, or one "
                f"declaring agent_inputs); {system.name} is {article} {system.kind} problem without agents: "
                "use ReachEnv (gym.make('Reach-v0', system=...))"
            )
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.render_mode = render_mode
        self.sim = SceneSimulator(self.scene, FLOAT)
        #: per-car outcomes (a MultiVehicle avoid scene), else one outcome shared by the team
        self.per_car = isinstance(system, MultiVehicle) and not system.problem.reaches
        self.possible_agents = list(inputs)
        self.agents: list[str] = []
        self._inputs = inputs
        self._agent_car = (
            {name: i for i, name in zip(system.control_cars, self.possible_agents)} if self.per_car else {}
        )
        self._obs_space = observation_space(system)
        self._act_spaces = {name: action_space(len(k)) for name, k in inputs.items()}
        # each agent's inputs are clipped on their own: a ball couples them (no built-in agent has one)
        require_box(system.control_bounds, "the PettingZoo env")
        self._centre = system.control_bounds.center
        self._half = system.control_bounds.half_width
        self._reaches = system.problem.reaches
        self._sampler = self.scene.sampler()
        self._record_trails = self.scene.trails and render_mode is not None
        self._trail_points = trail_points(self.scene) if self._record_trails and not self.per_car else None
        self._rng, _ = seeding.np_random(None)
        self._renderer = None
        self._state: list[float] = []
        self._crashed = [False] * system.num_cars if self.per_car else []
        self._collided = False
        self._steps = 0
        self._trails: list[list[tuple[float, float]]] = []

    @functools.cache  # noqa: B019 - PettingZoo's convention: one space object per agent
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Box:
        return self._act_spaces[agent]

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

    def _team_status(self) -> dict[str, Any]:
        """The system's margins at the current state, as :class:`ReachEnv` reports them at reset."""
        if not self._reaches:
            margin = self.sim.margin(self._state)
            return {"margin": margin, "collision": margin <= 0.0}
        target, constraint, collision, reached = self.sim.reach_status(self._state)
        return {
            "margin": constraint,
            "collision": bool(collision),
            "target_margin": target,
            "constraint_margin": constraint,
            "reached": bool(reached),
        }

    def _control(self, agent: str, u: list[float]) -> float | np.ndarray:
        """``info["control"]``: the agent's inputs as applied (a float for one input)."""
        indices = self._inputs[agent]
        return u[indices[0]] if len(indices) == 1 else np.array([u[k] for k in indices])

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
        self._steps = 0
        if not self.per_car:
            status = self._team_status()
            self._collided = status["collision"]
            if self._record_trails:
                self._trails = [[p] for p in self._trail_points(self._state)]
            if self._reaches:
                status["outcome"] = None
            return self._observations(), {a: {**status, "time": 0.0} for a in self.agents}
        self._crashed = [False] * self.system.num_cars
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
        u = list(self._centre)  # inputs of agents that are no longer live stay at their box centre
        for agent in self.agents:
            indices = self._inputs[agent]
            try:
                given = check_action(actions[agent], (len(indices),))
            except ValueError as err:  # name whose action it was: every agent's fails the same way
                raise ValueError(f"agent {agent!r}: {err}") from err
            for k, v in zip(indices, given.tolist()):
                u[k] = self._centre[k] + self._half[k] * (-1.0 if v < -1.0 else (1.0 if v > 1.0 else v))
        previous = self._state
        d = self.sim.disturbance(previous, self._rng)
        x = self.sim.advance(previous, u, d, self._rng)
        if self.per_car:
            n = self.system.num_cars
            for i, crashed in enumerate(self._crashed):
                if crashed:  # a crashed car stays where it stopped
                    x[2 * i], x[2 * i + 1], x[2 * n + i] = previous[2 * i], previous[2 * i + 1], previous[2 * n + i]
        self._state = x
        self._steps += 1
        step = self._per_car_step if self.per_car else self._team_step
        rewards, terminations, truncations, infos = step(u)
        observations = self._observations()
        self.agents = [a for a in self.agents if not (terminations[a] or truncations[a])]
        return observations, rewards, terminations, truncations, infos

    def _per_car_step(self, u: list[float]) -> tuple[dict, dict, dict, dict]:
        """Rewards, terminations, truncations and infos of each car's own collisions."""
        x = self._state
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
                "control": self._control(agent, u),
                "time": time,
            }
        if self.scene.terminate_on_collision:
            for i, collided in enumerate(hit):
                self._crashed[i] = self._crashed[i] or collided
        if self._record_trails:
            for i, (trail, (px, py, _)) in enumerate(zip(self._trails, self.system.car_poses(x, FLOAT))):
                if not self._crashed[i] or trail[-1] != (px, py):
                    trail.append((px, py))
        return rewards, terminations, truncations, infos

    def _team_step(self, u: list[float]) -> tuple[dict, dict, dict, dict]:
        """Rewards, terminations, truncations and infos of the system's one outcome, shared by every agent."""
        x = self._state
        status = self._team_status()
        collision = self._collided = status["collision"]
        out = bool(self.sim.out_of_arena(x))
        if self._reaches:
            terminated = bool(collision or status["reached"] or out)
        else:
            terminated = bool((collision and self.scene.terminate_on_collision) or out)
        truncated = not terminated and self._steps >= self.scene.max_steps
        common = {"margin": status["margin"], "collision": collision, "out_of_arena": out}
        if self._reaches:
            outcome = episode_outcome(collision, status["reached"], out, truncated)
            reward = OUTCOME_REWARDS[outcome] if outcome is not None else 0.0
            reach_keys = {k: status[k] for k in ("target_margin", "constraint_margin", "reached")}
            reach_keys["outcome"] = outcome
        else:
            reward = -1.0 if collision else 0.0
            reach_keys = {}
        if self._record_trails:
            for trail, p in zip(self._trails, self._trail_points(x)):
                trail.append(p)
        time = self._steps * self.scene.dt
        infos = {a: {**common, "control": self._control(a, u), "time": time, **reach_keys} for a in self.agents}
        return (
            dict.fromkeys(self.agents, reward),
            dict.fromkeys(self.agents, terminated),
            dict.fromkeys(self.agents, truncated),
            infos,
        )

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        if self._renderer is None:
            self._renderer = make_renderer(self.scene)
        trails = self._trails if self._record_trails else None
        time = self._steps * self.scene.dt
        if not self.per_car:
            return render_frame(self._renderer, self.system, self._state, time, trails, self._collided)
        poses = self.system.car_poses(self._state, FLOAT)
        return self._renderer.render(poses, time, trails, self._crashed)

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

    def control_indices(self, agent: str) -> tuple[int, ...]:
        """The indices of ``agent``'s inputs in the system's control vector."""
        if agent not in self._inputs:
            raise ValueError(f"unknown agent {agent!r}; agents are {self.possible_agents}")
        return self._inputs[agent]

    def control_index(self, agent: str) -> int:
        """The index of the one input (a car's turn rate) ``agent`` acts in the system's control vector;
        ``ValueError`` for an agent of several inputs (use :meth:`control_indices`)."""
        indices = self.control_indices(agent)
        if len(indices) != 1:
            raise ValueError(f"agent {agent!r} acts inputs {indices} of {self.system.name}; use control_indices")
        return indices[0]

    @property
    def state_space(self) -> spaces.Box:
        return self._obs_space


def parallel_env(
    scene: str | Scene | None = None, render_mode: str | None = None, *, system: Any = None, **overrides: Any
) -> MultiVehicleParallelEnv:
    """PettingZoo-style constructor: ``parallel_env("head-on")``, ``parallel_env("four-car-12d")``, or
    a system with agents, ``parallel_env(system="narrowpassage")``; ``parallel_env()`` is ``"three-car-9d"``."""
    return MultiVehicleParallelEnv(scene, render_mode=render_mode, system=system, **overrides)
