"""Native vector environment: N copies of a scene advanced as one NumPy batch.

``gym.make_vec("Air3D-v0", num_envs=N, vectorization_mode="vector_entry_point")`` builds it, and for any
system ``gym.make_vec("Reach-v0", num_envs=N, system=...)`` or :func:`reach_envs.make_vector_env`. Each
sub-environment ``i`` owns a generator seeded like Gymnasium's ``SyncVectorEnv`` seeds it
(``seed + i``), so initial states, including those of automatic resets, equal those of single
environments reset with the same seeds, and deterministic scenes match them step for step. Scenes
with per-step randomness (process noise, a random disturbance) draw those numbers for the whole batch
from one vector-level generator: the same distribution, not the same draws.

Autoreset follows Gymnasium's default ``NEXT_STEP`` mode: the step after an episode ends resets that
sub-environment, returns its first observation with reward 0, and ignores its action.

Termination, rewards and ``info`` follow the system's kind as in :class:`~reach_envs.env.ReachEnv`,
per sub-environment, as ``(num_envs,)`` arrays: a reach kind's ``info["outcome"]`` is an object
array of ``"reached"``, ``"collided"``, ``"out_of_arena"``, ``"timeout"`` or ``None`` (running, or
reset on this step).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from reach.systems.arrays import NUMPY
from reach_envs.regions import COLLIDED, OUT_OF_ARENA, OUTCOME_REWARDS, REACHED, TIMEOUT
from reach_envs.scenes import Scene, env_scene
from reach_envs.simulator import SceneSimulator
from reach_envs.spaces import (
    action_space,
    check_action,
    check_reset_options,
    check_state,
    inputs_of_actions,
    observation_space,
)
from reach_envs.views import make_renderer, render_frame


class ReachVectorEnv(VectorEnv):
    """``num_envs`` environments of one scene stepped as a batch (see the module docstring).

    ``scene`` (a :class:`Scene` or a named scene) or ``system`` (an instance, a registered name or an
    import path): exactly one must be given, as for :class:`~reach_envs.env.ReachEnv`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 1,
        scene: str | Scene | None = None,
        render_mode: str | None = None,
        *,
        system: Any = None,
        **overrides: Any,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.scene = env_scene(scene, system, **overrides)
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / self.scene.dt))}
        system = self.system = self.scene.system
        self.sim = SceneSimulator(self.scene, NUMPY)
        self.single_observation_space = observation_space(system)
        self.single_action_space = action_space(system.control_dim)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._action_shape = (num_envs, system.control_dim)
        self._sampler = self.scene.sampler()
        self._rngs = [seeding.np_random(None)[0] for _ in range(num_envs)]
        self._seeded = [False] * num_envs
        self._step_rng = seeding.np_random(None)[0]
        self._step_rng_seeded = False
        n = system.state_dim
        self._state = [np.zeros(num_envs) for _ in range(n)]
        self._steps = np.zeros(num_envs, dtype=np.int64)
        self._autoreset = np.zeros(num_envs, dtype=bool)
        self._crashed = np.zeros(num_envs, dtype=bool)
        self._renderer = None
        self._reaches = system.problem.reaches

    # ------------------------------------------------------------------ helpers
    def _reach_info(self, info: dict, status: tuple, ended: np.ndarray | None = None, out: Any = False) -> dict:
        """``info`` of a reach kind with its margins, flags and outcome from ``status`` (the simulator's
        :meth:`~reach_envs.simulator.SceneSimulator.reach_status`); ``ended`` masks the sub-envs whose
        episode ended on this step (``None`` at reset: no outcome yet)."""
        target, constraint, collision, reached = status
        info.update(margin=constraint, collision=collision)
        info.update(target_margin=target, constraint_margin=constraint, reached=reached)
        outcome = np.full(self.num_envs, None, dtype=object)
        if ended is not None:  # the first match wins, as in reach_envs.regions.episode_outcome
            for name, mask in ((TIMEOUT, True), (OUT_OF_ARENA, out), (REACHED, reached), (COLLIDED, collision)):
                outcome[ended & mask] = name
        info["outcome"] = outcome
        return info

    def _sample_into(self, indices: np.ndarray, states: np.ndarray | None = None) -> None:
        """Draw fresh initial states for the given sub-environments (a loop over resets only)."""
        x = np.stack(self._state, axis=-1)
        for k, i in enumerate(indices):
            if states is not None:
                xi = check_state(states[k], self.system)
            else:
                xi = check_state(self._sampler.sample(self.system, self._rngs[i]), self.system)
            x[i] = xi
        self._state = self.system.wrap_columns(NUMPY.unbind(x), NUMPY)
        self._steps[indices] = 0
        self._crashed[indices] = False

    def _observation(self) -> np.ndarray:
        return np.stack(self._state, axis=-1).astype(np.float32)

    # ------------------------------------------------------------------ gymnasium API
    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict]:
        """Reset sub-environments; ``options`` may hold ``reset_mask`` (bool ``(N,)``) and ``state`` (``(N, n)``)."""
        options = check_reset_options(options, ("reset_mask", "state"))
        n = self.num_envs
        if seed is None:
            seeds: list[int | None] = [None] * n
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(n)]
        else:
            seeds = list(seed)
            if len(seeds) != n:
                raise ValueError(f"seed list must have num_envs={n} entries, got {len(seeds)}")
        mask = np.ones(n, dtype=bool)
        if options and options.get("reset_mask") is not None:
            mask = np.asarray(options["reset_mask"], dtype=bool)
            if mask.shape != (n,):
                raise ValueError(f"reset_mask must have shape ({n},), got {mask.shape}")
        indices = np.flatnonzero(mask)
        # Like a single env: a seed re-seeds; no seed keeps a generator's stream going (entropy-seeded
        # the first time), so later resets continue reproducibly after one seeded reset.
        for i in indices:
            if seeds[i] is not None or not self._seeded[i]:
                self._rngs[i] = seeding.np_random(seeds[i])[0]
                self._seeded[i] = True
        if seed is not None or not self._step_rng_seeded:
            first = seeds[0] if seeds[0] is not None else None
            self._step_rng = np.random.default_rng(None if first is None else [first, 0x5EED])
            self._step_rng_seeded = True
        states = None
        if options and options.get("state") is not None:
            states = np.asarray(options["state"], dtype=np.float64)
            if states.shape != (n, self.system.state_dim):
                raise ValueError(f"options['state'] must have shape ({n}, {self.system.state_dim}), got {states.shape}")
            states = states[indices]
        self._sample_into(indices, states)
        self._autoreset[indices] = False
        if self._reaches:
            return self._observation(), self._reach_info({"time": np.zeros(n)}, self.sim.reach_status(self._state))
        margin = self.sim.margin(self._state)
        info = {"margin": margin, "collision": margin <= 0.0, "time": np.zeros(n)}
        return self._observation(), info

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        u = list(inputs_of_actions(check_action(actions, self._action_shape), self.system.control_bounds).T)
        sim = self.sim
        d = sim.disturbance(self._state, self._step_rng)
        self._state = sim.advance(self._state, u, d, self._step_rng)
        self._steps += 1
        resetting = np.flatnonzero(self._autoreset)
        if resetting.size:
            self._sample_into(resetting)
        out = np.broadcast_to(sim.out_of_arena(self._state), (self.num_envs,))
        if self._reaches:
            status = sim.reach_status(self._state)
            _, _, collision, reached = status
            terminated = out | collision | reached
            reward = np.where(reached, OUTCOME_REWARDS[REACHED], np.where(collision, OUTCOME_REWARDS[COLLIDED], 0.0))
        else:
            margin = sim.margin(self._state)
            collision = margin <= 0.0
            terminated = out | (collision & self.scene.terminate_on_collision)
            reward = np.where(collision, -1.0, 0.0)
        truncated = ~terminated & (self._steps >= self.scene.max_steps)
        if resetting.size:
            terminated[resetting] = False
            truncated[resetting] = False
            reward[resetting] = 0.0
        self._crashed = collision
        self._autoreset = terminated | truncated
        d_arr = (
            np.stack([np.broadcast_to(v, (self.num_envs,)) for v in d], axis=-1) if d else np.zeros((self.num_envs, 0))
        )
        info = {
            "margin": None if self._reaches else margin,
            "collision": collision,
            "out_of_arena": out.copy(),
            "control": np.stack(u, axis=-1),
            "disturbance": d_arr,
            "time": self._steps * self.scene.dt,
        }
        if self._reaches:
            info = self._reach_info(info, status, terminated | truncated, out)
        return self._observation(), reward, terminated, truncated, info

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One frame per sub-environment (``render_mode="rgb_array"``)."""
        if self.render_mode is None:
            return None
        if self._renderer is None:
            self._renderer = make_renderer(self.scene)
        x = np.stack(self._state, axis=-1).tolist()
        dt = self.scene.dt
        return tuple(
            render_frame(self._renderer, self.system, x[i], float(self._steps[i] * dt), None, bool(self._crashed[i]))
            for i in range(self.num_envs)
        )

    def close_extras(self, **kwargs: Any) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    @property
    def elapsed(self) -> np.ndarray:
        """Seconds since each sub-environment's last reset, ``(num_envs,)``."""
        return self._steps * self.scene.dt

    @property
    def state(self) -> np.ndarray:
        """Current states ``(num_envs, n)`` in float64."""
        return np.stack(self._state, axis=-1)
