"""Gymnasium and PettingZoo environments of fleet scenes (:mod:`reach_envs.fleet_scenes`).

:class:`FleetEnv` is one agent driving all N cars: the action is every car's turn rate normalised to
``[-1, 1]^N`` (``-1`` and ``1`` are the car's turn-rate bound; values outside are clipped; NaN, inf
and wrong shapes raise ``ValueError``). :class:`FleetParallelEnv` is a PettingZoo ``ParallelEnv`` with
one agent per car, ``car_1`` ... ``car_N``, each acting its own normalised turn rate as a ``(1,)``
action. Both step the batched :class:`~reach_envs.fleet.FleetSimulator` on a batch of one.

Observations (float32, shape ``(5N,)``, the same for every agent) are the fleet state in
``MultiVehicle`` order followed by the goals, ``(x1, y1, ..., xN, yN, th1, ..., thN, gx1, gy1, ...,
gxN, gyN)``. A car that collided or arrived leaves the scene (it stays where it stopped, and takes
no part in later collisions).

Rewards are not shaped: +1 for a car's arrival, -1 for a car's collision (:class:`FleetEnv`: the sum
over its cars on the step). :class:`FleetEnv` *terminates* once no car is left and is *truncated*
at the scene's horizon; in :class:`FleetParallelEnv` an agent terminates on its car's collision or
arrival, and the agents left are truncated at the horizon.

``info`` (per agent in :class:`FleetParallelEnv`, for that car) holds ``collision`` and ``arrived``
(this step), ``crashed`` and ``reached`` (so far), ``present`` and ``time`` (seconds);
:class:`FleetEnv` gives the first four as ``(N,)`` bool arrays. ``reset(options={"state": x,
"goals": g})`` starts from a given ``(3N,)`` state and ``(N, 2)`` goals instead of sampling.
``render_mode="rgb_array"`` draws the fleet (:func:`~reach_envs.fleet_render.render_fleet`).
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from reach.validation import settings_from
from reach_envs.fleet import FleetSimulator
from reach_envs.fleet_render import FleetRenderer
from reach_envs.fleet_scenes import FleetScene
from reach_envs.spaces import EpisodeOverError, check_action, check_reset_options


def fleet_scene(scene: FleetScene | str | None = None, **fields: Any) -> FleetScene:
    """A :class:`FleetScene` from a scene, a layout name or ``None`` (the defaults), with ``fields``
    (its field names) replacing the scene's; unknown fields raise ``ValueError`` naming them."""
    if isinstance(scene, str):
        fields = {"layout": scene, **fields}
        scene = None
    return settings_from(FleetScene, scene, fields, "FleetScene")


class FleetEpisode:
    """One episode of a fleet scene on a batch of one: the state, goals, presence and tallies that both
    environments keep, and the observation and frame they show."""

    def __init__(self, scene: FleetScene, render_mode: str | None) -> None:
        if render_mode is not None and render_mode != "rgb_array":
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.scene = scene
        self.render_mode = render_mode
        self.sim = FleetSimulator(scene)
        self.n = scene.n_cars
        self.bound = torch.tensor(scene.max_turn_rates, dtype=torch.float64)
        self.steps = 0
        self.x = torch.zeros(1, 3 * self.n, dtype=torch.float64)
        self.goals = torch.zeros(1, self.n, 2, dtype=torch.float64)
        self.present = torch.zeros(1, self.n, dtype=torch.bool)
        self.crashed = torch.zeros(1, self.n, dtype=torch.bool)
        self.reached = torch.zeros(1, self.n, dtype=torch.bool)
        self.renderer: FleetRenderer | None = None

    def observation_space(self) -> spaces.Box:
        """float32 ``(5N,)``: headings in ``[-pi, pi]``, positions and goals unbounded."""
        low = np.full(5 * self.n, -np.inf, dtype=np.float32)
        low[2 * self.n : 3 * self.n] = -np.pi
        high = -low
        high[2 * self.n : 3 * self.n] = np.pi
        return spaces.Box(low=low, high=high, dtype=np.float32)

    def start(self, options: dict[str, Any], rng: np.random.Generator) -> None:
        """Reset to ``options``' state and goals, or to a fresh sample drawn with ``rng``."""
        given = [k for k in ("state", "goals") if options.get(k) is not None]
        if given and len(given) != 2:
            raise ValueError(f"reset options 'state' and 'goals' go together; got only {given}")
        if given:
            x = self.sim.check_state(_tensor(options["state"], "state").reshape(1, -1), "state")
            goals = self.sim.check_goals(_tensor(options["goals"], "goals").reshape(1, self.n, -1), 1)
        else:
            x, goals = self.scene.sample(1, rng)
        self.x, self.goals = x, goals
        self.present = torch.ones(1, self.n, dtype=torch.bool)
        self.crashed = torch.zeros(1, self.n, dtype=torch.bool)
        self.reached = torch.zeros(1, self.n, dtype=torch.bool)
        self.steps = 0

    def advance(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One step under normalised actions ``(N,)`` (clipped to ``[-1, 1]``); ``(collided, arrived)``
        as ``(N,)`` bool arrays."""
        u = torch.from_numpy(np.clip(actions, -1.0, 1.0))[None] * self.bound
        self.x, hit, arrived, self.present = self.sim.step(self.x, u, self.present, self.goals)
        self.crashed |= hit
        self.reached |= arrived
        self.steps += 1
        return hit[0].numpy(), arrived[0].numpy()

    @property
    def time(self) -> float:
        return self.steps * self.scene.dt

    @property
    def over_time(self) -> bool:
        return self.steps >= self.scene.max_steps

    def observation(self) -> np.ndarray:
        return torch.cat([self.x[0], self.goals[0].reshape(-1)]).numpy().astype(np.float32)

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        if self.renderer is None:
            self.renderer = FleetRenderer(self.scene)
        return self.renderer.render(self.x[0], self.goals[0], self.present[0], self.time, self.crashed[0])

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None


def _tensor(value: Any, what: str) -> torch.Tensor:
    """A user-given state or goals as a float64 tensor (the simulator's checks name the rest)."""
    raw = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
    if raw.dtype.kind not in "iuf":
        raise ValueError(f"{what} must hold real numbers, got {value!r} ({raw.dtype})")
    return torch.from_numpy(raw.astype(np.float64))


class FleetEnv(gym.Env[np.ndarray, np.ndarray]):
    """One agent driving a whole fleet (module docstring).

    Args:
        scene: a :class:`FleetScene`, a layout name, or ``None`` for the defaults.
        render_mode: ``None`` or ``"rgb_array"``.
        **fields: :class:`FleetScene` fields to set, e.g. ``layout="intersection", n_cars=32``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, scene: FleetScene | str | None = None, render_mode: str | None = None, **fields: Any) -> None:
        self.scene = fleet_scene(scene, **fields)
        self.episode = FleetEpisode(self.scene, render_mode)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / self.scene.dt))}
        n = self.scene.n_cars
        self.observation_space = self.episode.observation_space()
        self.action_space = spaces.Box(low=-1.0, high=1.0, shape=(n,), dtype=np.float32)
        self._over: str | None = "before reset()"

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode: sampled from the scene, or ``options={"state": x, "goals": g}``."""
        options = check_reset_options(options, ("state", "goals"))
        super().reset(seed=seed)
        self.episode.start(options, self.np_random)
        self._over = None
        none = np.zeros(self.scene.n_cars, dtype=bool)
        return self.episode.observation(), self._info(none, none)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._over is not None:
            raise EpisodeOverError(f"step() called {self._over}; call reset() to start an episode")
        hit, arrived = self.episode.advance(check_action(action, (self.scene.n_cars,)))
        terminated = not bool(self.episode.present.any())
        truncated = not terminated and self.episode.over_time
        if terminated or truncated:
            self._over = "after the episode was " + ("terminated" if terminated else "truncated")
        reward = float(arrived.sum()) - float(hit.sum())
        return self.episode.observation(), reward, terminated, truncated, self._info(hit, arrived)

    def _info(self, hit: np.ndarray, arrived: np.ndarray) -> dict[str, Any]:
        e = self.episode
        return {
            "collision": hit,
            "arrived": arrived,
            "crashed": e.crashed[0].numpy().copy(),
            "reached": e.reached[0].numpy().copy(),
            "present": e.present[0].numpy().copy(),
            "time": e.time,
        }

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array'")
        return self.episode.render()

    def close(self) -> None:
        self.episode.close()

    @property
    def state(self) -> np.ndarray:
        """The fleet state ``(3N,)`` in float64."""
        return self.episode.x[0].numpy().copy()

    @property
    def goals(self) -> np.ndarray:
        """The goals ``(N, 2)`` in float64."""
        return self.episode.goals[0].numpy().copy()


class FleetParallelEnv(ParallelEnv):
    """One PettingZoo agent per car, ``car_1`` ... ``car_N`` (module docstring).

    Args:
        scene: a :class:`FleetScene`, a layout name, or ``None`` for the defaults.
        render_mode: ``None`` or ``"rgb_array"``.
        **fields: :class:`FleetScene` fields to set, e.g. ``n_cars=32``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "reach_fleet_v0", "is_parallelizable": True}

    def __init__(self, scene: FleetScene | str | None = None, render_mode: str | None = None, **fields: Any) -> None:
        self.scene = fleet_scene(scene, **fields)
        self.episode = FleetEpisode(self.scene, render_mode)
        self.render_mode = render_mode
        self.possible_agents = [f"car_{i + 1}" for i in range(self.scene.n_cars)]
        self.agents: list[str] = []
        self._car = {a: i for i, a in enumerate(self.possible_agents)}
        self._obs_space = self.episode.observation_space()
        self._act_space = {
            a: spaces.Box(low=-1.0, high=1.0, shape=(1,), dtype=np.float32) for a in self.possible_agents
        }
        self._rng, _ = seeding.np_random(None)

    @functools.cache  # noqa: B019 - PettingZoo's convention: one space object per agent
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Box:
        return self._act_space[agent]

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        if seed is not None:
            self._rng, _ = seeding.np_random(seed)
        options = check_reset_options(options, ("state", "goals"), unknown_keys="warn")
        self.episode.start(options, self._rng)
        self.agents = list(self.possible_agents)
        obs = self.episode.observation()
        infos = {a: self._info(a, False, False) for a in self.agents}
        return {a: obs.copy() for a in self.agents}, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        missing = [a for a in self.agents if a not in actions]
        unknown = [a for a in actions if a not in self.agents]
        if missing or unknown:
            raise ValueError(
                f"actions must have one entry per live agent {self.agents}; missing {missing}, unknown {unknown}"
            )
        a = np.zeros(self.scene.n_cars)  # cars that left the scene take no action
        for agent in self.agents:
            try:
                a[self._car[agent]] = check_action(actions[agent], (1,))[0]
            except ValueError as err:  # name whose action it was
                raise ValueError(f"agent {agent!r}: {err}") from err
        hit, arrived = self.episode.advance(a)
        truncate = self.episode.over_time
        obs = self.episode.observation()
        observations, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for agent in self.agents:
            car = self._car[agent]
            observations[agent] = obs.copy()
            rewards[agent] = (1.0 if arrived[car] else 0.0) - (1.0 if hit[car] else 0.0)
            terminations[agent] = bool(hit[car] or arrived[car])
            truncations[agent] = truncate and not terminations[agent]
            infos[agent] = self._info(agent, bool(hit[car]), bool(arrived[car]))
        self.agents = [a for a in self.agents if not (terminations[a] or truncations[a])]
        return observations, rewards, terminations, truncations, infos

    def _info(self, agent: str, hit: bool, arrived: bool) -> dict[str, Any]:
        e, car = self.episode, self._car[agent]
        return {
            "collision": hit,
            "arrived": arrived,
            "crashed": bool(e.crashed[0, car]),
            "reached": bool(e.reached[0, car]),
            "present": bool(e.present[0, car]),
            "time": e.time,
        }

    def render(self) -> np.ndarray | None:
        return self.episode.render()

    def close(self) -> None:
        self.episode.close()

    def state(self) -> np.ndarray:
        """The global observation (float32), as PettingZoo's ``state()`` API expects."""
        return self.episode.observation()

    @property
    def state_space(self) -> spaces.Box:
        return self._obs_space
