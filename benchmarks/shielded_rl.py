"""Shielded reinforcement learning on Air3D: a stable-baselines3 agent trained through the safety
filter (:class:`safety.SafetyFilterWrapper`) against the same agent trained without it.

Run: ``python benchmarks/shielded_rl.py`` (``--seeds 0,1,2``, ``--steps 30000`` environment steps
per agent, ``--eval-episodes 200``; ``--quick`` for a smoke run; ``--out FILE.json`` keeps the
results and ``--report FILE.json`` prints their tables again without training). Needs the ``rl`` extra
(``pip install -c constraints.txt -e ".[rl]"``: stable-baselines3).

The task: ``Air3D-v0`` as shipped (the pursuer turns toward the evader, equal speeds and turn rates,
episodes of 1.1 s, 55 steps of 0.02 s, ending at the first collision), and a goal for the evader:
a point 0.7 away at a bearing drawn in [-45, 45] degrees of its initial heading, reached within 0.15
(:class:`studies.goal_tasks.EvaderGoalTask`, the filter studies' task, which tracks the evader's world
pose from the turn rates actually applied). The agent sees the relative state (pursuer position,
the sine and cosine of the relative heading), the goal in the evader's frame and the time left; its
reward per step is the progress toward the goal (as a share of the initial distance), +1 on
reaching it (the episode ends there) and the env's -1 on a collision.

Fair comparison, one rule per point:

- the same seeds: a seed fixes the agent's initialisation, the env's starts and goals, and PPO's
  sampling, for the shielded and the unshielded agent alike;
- the same budget: ``--steps`` environment steps each (the filter's own evaluations are free);
- the same starts: uniform over the states where the filter's value function says escape is
  possible, ``V(x, 1.1) > --start-margin`` (from inside the BRT a worst-case pursuer collides
  whatever anyone does, so no shield can be blamed there);
- the same reward: that of the state reached by the action *applied*; the shielded agent is charged
  for nothing else (``--penalty`` adds a cost per intervention, off by default);
- what the agent learns from: its own proposed action. PPO stores the action it sampled, with its
  log-probability, and the reward that followed; the filter is part of the environment as the agent
  sees it. (Storing the filter's action would make PPO's data off-policy.)

Reported per arm and seed: training episodes, collisions during training, goals reached, the mean
training return; and at evaluation (``--eval-episodes`` deterministic episodes from fixed starts
and goals shared by every agent, ``--eval-seed``), with the filter off and on: collisions, goals
reached, mean return and (filter on) the share of steps where the filter intervened. The filter is
the wrapper's default: the switch with the greedy backup input, threshold ``2 * rate bound * dt``
(0.06 on Air3D), on the shipped network ``pretrained:air3d``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

import reach_envs  # noqa: F401  (registers Air3D-v0)
from reach.value_function import ValueFunction
from safety import SafetyFilterWrapper, load_value_function
from studies.filter_episodes import outside_states
from studies.goal_tasks import EvaderGoalTask

#: the filter's value function: the network shipped for Air3D-v0
VALUE_FUNCTION = "pretrained:air3d"
ARMS = ("unshielded", "shielded")
#: starts are drawn from this many states of ``{V > margin}`` per seed (and the evaluation's own set)
POOL = 4096


class EvaderGoal(gym.Wrapper):
    """Air3D with a goal for the evader: the observation, reward and end of an episode of the task.

    Sits *inside* the safety filter, so it sees the action the filter applied (its ``info["control"]``,
    physical units) and tracks the evader's pose with it. Observation (float32): pursuer ``x, y`` in
    the evader's frame, ``sin psi, cos psi``, the goal in the evader's frame, the share of the
    episode left. Reward: progress toward the goal over its initial distance, ``goal_bonus`` on
    reaching it (which ends the episode), and the env's reward (-1 on a collision) times
    ``collision_cost``.
    """

    def __init__(self, env: gym.Env, goal_bonus: float = 1.0, collision_cost: float = 1.0) -> None:
        super().__init__(env)
        base = env.unwrapped
        self.task = EvaderGoalTask(base.system)
        self.goal_bonus, self.collision_cost = float(goal_bonus), float(collision_cost)
        self.dt, self.horizon = base.scene.dt, base.scene.episode_horizon
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(7,), dtype=np.float32)
        self._distance = 0.0

    def _goal_distance(self) -> float:
        return float(np.hypot(*(self.task.goals[0] - self.task.pose[0, :2])))

    def _observation(self, obs: np.ndarray, time_s: float) -> np.ndarray:
        x, y, psi = (float(v) for v in obs)
        ex, ey, eth = self.task.pose[0]
        gx, gy = self.task.goals[0] - (ex, ey)
        c, s = math.cos(eth), math.sin(eth)  # the goal, rotated into the evader's frame
        left = max(0.0, 1.0 - time_s / self.horizon)
        return np.array([x, y, math.sin(psi), math.cos(psi), c * gx + s * gy, -s * gx + c * gy, left], np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        obs, info = self.env.reset(seed=seed, options=options)
        # the goal is drawn from the env's generator after the start: one seed fixes both
        self.task.reset(self.env.unwrapped.state[None], self.env.unwrapped.np_random)
        self._distance = self._goal_distance()
        info["goal_reached"] = False
        return self._observation(obs, 0.0), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        before = self._goal_distance()
        self.task.advance(
            self.env.unwrapped.state[None], np.asarray(info["control"])[None], self.dt, np.ones(1, bool), info["time"]
        )
        reached = bool(self.task.reached[0]) and not info["collision"]
        task_reward = (before - self._goal_distance()) / self._distance + (self.goal_bonus if reached else 0.0)
        info["goal_reached"] = reached
        terminated = terminated or reached
        return (
            self._observation(obs, info["time"]),
            task_reward + self.collision_cost * float(reward),
            terminated,
            truncated and not reached,
            info,
        )


@dataclass
class EpisodeLog:
    """What happened in the episodes one env ran (its :class:`Recorder` fills it)."""

    returns: list[float] = field(default_factory=list)
    collisions: int = 0
    goals: int = 0
    steps: int = 0
    interventions: int = 0

    @property
    def episodes(self) -> int:
        return len(self.returns)


class Recorder(gym.Wrapper):
    """The outermost layer: logs each episode's task return, collision, goal and the filter's
    interventions, and charges ``penalty`` per intervention to the reward the agent sees (the logged
    return leaves it out, so returns compare across arms)."""

    def __init__(self, env: gym.Env, penalty: float = 0.0) -> None:
        super().__init__(env)
        self.log = EpisodeLog()
        self.penalty = float(penalty)
        self._return = 0.0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        self._return = 0.0
        return self.env.reset(seed=seed, options=options)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        intervened = bool(info.get("filter_intervened", False))
        self._return += float(reward)
        self.log.steps += 1
        self.log.interventions += intervened
        if terminated or truncated:
            self.log.returns.append(self._return)
            self.log.collisions += bool(info["collision"])
            self.log.goals += bool(info["goal_reached"])
        return obs, float(reward) - self.penalty * intervened, terminated, truncated, info


def start_pool(value_function: ValueFunction, n: int, margin: float, seed: int) -> np.ndarray:
    """``n`` float64 states uniform on ``{V(x, T) > margin}`` of the filter's value function, seeded."""
    return outside_states(value_function, n, margin, seed)


def make_env(
    starts: np.ndarray, value_function: ValueFunction | None, penalty: float = 0.0
) -> tuple[gym.Env, EpisodeLog]:
    """The task env, its starts drawn from ``starts`` by the env's generator; filtered through
    :class:`SafetyFilterWrapper` when ``value_function`` is given. Returns the env and its log."""
    pool = np.array(starts)
    env: gym.Env = EvaderGoal(gym.make("Air3D-v0", initial_state=lambda rng: pool[rng.integers(len(pool))]))
    if value_function is not None:
        env = SafetyFilterWrapper(env, value_function)
    recorder = Recorder(env, penalty)
    return recorder, recorder.log


@dataclass
class Evaluation:
    """Deterministic episodes of a trained agent from the shared evaluation starts."""

    episodes: int
    collisions: int
    goals: int
    mean_return: float
    intervention_rate: float | None  # interventions per step; None without the filter


def evaluate(
    model: Any, starts: np.ndarray, value_function: ValueFunction | None, episodes: int, seed: int
) -> Evaluation:
    """Run ``episodes`` deterministic episodes (episode ``k`` reset with seed ``seed + k``: the same
    start and goal for every agent), filtered when ``value_function`` is given."""
    env, log = make_env(starts, value_function)
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
    return Evaluation(
        episodes=log.episodes,
        collisions=log.collisions,
        goals=log.goals,
        mean_return=float(np.mean(log.returns)),
        intervention_rate=log.interventions / log.steps if value_function is not None else None,
    )


class GoalSeeking:
    """The reference that learns nothing: the filter studies' nominal policy (turn toward the goal at
    ``gain`` times the heading error, clipped to the turn-rate box), on the agent's observation."""

    def __init__(self, gain: float = 3.0, max_turn_rate: float = 3.0) -> None:
        self.gain, self.max_turn_rate = gain, max_turn_rate

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        """The action for one observation, with stable-baselines3's ``predict`` signature."""
        error = math.atan2(float(obs[5]), float(obs[4]))  # the goal's bearing in the evader's frame
        return np.array([np.clip(self.gain * error / self.max_turn_rate, -1.0, 1.0)], np.float32), None


@dataclass
class ArmResult:
    """One agent: how its training went and how it did at evaluation, filter off and on."""

    arm: str  # "unshielded", "shielded", or "shielded, penalty P" with an intervention penalty
    seed: int
    steps: int
    train_episodes: int
    train_collisions: int
    train_goals: int
    train_mean_return: float
    train_intervention_rate: float | None
    train_wall_s: float
    eval_off: Evaluation | None = None
    eval_on: Evaluation | None = None
    eval_wall_s: float = 0.0


def train_arm(
    arm: str,
    seed: int,
    steps: int,
    value_function: ValueFunction,
    *,
    start_margin: float = 0.1,
    penalty: float = 0.0,
    eval_starts: np.ndarray | None = None,
    eval_episodes: int = 0,
    eval_seed: int = 10_000,
    ppo: dict[str, Any] | None = None,
) -> ArmResult:
    """Train one PPO agent for ``steps`` env steps, through the filter (``arm="shielded"``) or not,
    then evaluate it on ``eval_episodes`` episodes from ``eval_starts``, filter off and on."""
    from stable_baselines3 import PPO  # lazy: the optional `rl` extra, needed only when an agent is trained

    if arm not in ARMS:
        raise ValueError(f"arm must be one of {ARMS}, got {arm!r}")
    starts = start_pool(value_function, POOL, start_margin, seed)
    env, log = make_env(starts, value_function if arm == "shielded" else None, penalty if arm == "shielded" else 0.0)
    env.reset(seed=seed)  # seeds the env's generator: the starts and goals of every training episode
    settings = {"n_steps": 512, "batch_size": 64, "n_epochs": 10, "learning_rate": 3e-4, "gamma": 0.99}
    settings.update(ppo or {})
    model = PPO("MlpPolicy", env, seed=seed, device="cpu", verbose=0, **settings)
    start = time.perf_counter()
    model.learn(total_timesteps=steps)
    result = ArmResult(
        arm=f"{arm}, penalty {penalty:g}" if arm == "shielded" and penalty else arm,
        seed=seed,
        steps=steps,
        train_episodes=log.episodes,
        train_collisions=log.collisions,
        train_goals=log.goals,
        train_mean_return=float(np.mean(log.returns)) if log.returns else float("nan"),
        train_intervention_rate=log.interventions / max(log.steps, 1) if arm == "shielded" else None,
        train_wall_s=time.perf_counter() - start,
    )
    if eval_episodes and eval_starts is not None:
        start = time.perf_counter()
        result.eval_off = evaluate(model, eval_starts, None, eval_episodes, eval_seed)
        result.eval_on = evaluate(model, eval_starts, value_function, eval_episodes, eval_seed)
        result.eval_wall_s = time.perf_counter() - start
    return result


@dataclass
class Study:
    """Every trained agent, and the goal-seeking reference's evaluation (filter off, on)."""

    results: list[ArmResult] = field(default_factory=list)
    reference: tuple[Evaluation, Evaluation] | None = None


def run_study(
    seeds: Sequence[int],
    steps: int,
    eval_episodes: int,
    *,
    arms: Sequence[str] = ARMS,
    start_margin: float = 0.1,
    penalty: float = 0.0,
    eval_seed: int = 10_000,
    value_function: ValueFunction | str = VALUE_FUNCTION,
    reference: bool = True,
    report: Any = None,
) -> Study:
    """Every arm on every seed, same budget, same evaluation starts; ``report(result)`` after each.
    ``reference``: also evaluate :class:`GoalSeeking` (no learning) on those starts, filter off and on."""
    vf = (
        value_function
        if isinstance(value_function, ValueFunction)
        else load_value_function(value_function).value_function
    )
    eval_starts = start_pool(vf, POOL, start_margin, eval_seed)
    study = Study()
    if reference and eval_episodes:
        study.reference = (
            evaluate(GoalSeeking(), eval_starts, None, eval_episodes, eval_seed),
            evaluate(GoalSeeking(), eval_starts, vf, eval_episodes, eval_seed),
        )
    results = study.results
    for seed in seeds:
        for arm in arms:
            r = train_arm(
                arm,
                seed,
                steps,
                vf,
                start_margin=start_margin,
                penalty=penalty,
                eval_starts=eval_starts,
                eval_episodes=eval_episodes,
                eval_seed=eval_seed,
            )
            results.append(r)
            if report is not None:
                report(r)
    return study


def _share(n: int, of: int) -> str:
    return f"{n} ({100 * n / of:.1f} %)" if of else "-"


def _rate(rate: float | None) -> str:
    return "-" if rate is None else f"{100 * rate:.1f} %"


def _pooled(evaluations: Sequence[Evaluation]) -> Evaluation:
    """Several seeds' evaluations as one: episodes, collisions and goals summed, returns and
    intervention rates averaged over the seeds."""
    rates = [e.intervention_rate for e in evaluations if e.intervention_rate is not None]
    return Evaluation(
        episodes=sum(e.episodes for e in evaluations),
        collisions=sum(e.collisions for e in evaluations),
        goals=sum(e.goals for e in evaluations),
        mean_return=float(np.mean([e.mean_return for e in evaluations])),
        intervention_rate=float(np.mean(rates)) if rates else None,
    )


def _eval_row(agent: str, seed: str, off: Evaluation, on: Evaluation) -> str:
    return (
        f"| {agent} | {seed} | {_share(off.collisions, off.episodes)} | {_share(on.collisions, on.episodes)} | "
        f"{_share(off.goals, off.episodes)} | {_share(on.goals, on.episodes)} | {off.mean_return:.3f} | "
        f"{on.mean_return:.3f} | {_rate(on.intervention_rate)} |"
    )


def tables(study: Study) -> str:
    """Markdown tables: training per agent and seed, then evaluation with the filter off and on; a
    bold row per arm pools its seeds (counts summed, returns and rates averaged over seeds)."""
    results = study.results
    arms = list(dict.fromkeys(r.arm for r in results))
    lines = [
        "| agent | seed | training episodes | collisions in training | goals in training | mean training return "
        "| interventions |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {r.arm} | {r.seed} | {r.train_episodes} | {_share(r.train_collisions, r.train_episodes)} | "
            f"{_share(r.train_goals, r.train_episodes)} | {r.train_mean_return:.3f} | "
            f"{_rate(r.train_intervention_rate)} |"
        )
    for arm in arms:
        rs = [r for r in results if r.arm == arm]
        eps, col, goals = (sum(getattr(r, f"train_{k}") for r in rs) for k in ("episodes", "collisions", "goals"))
        mean = float(np.mean([r.train_mean_return for r in rs]))
        rates = [r.train_intervention_rate for r in rs if r.train_intervention_rate is not None]
        rate = _rate(float(np.mean(rates)) if rates else None)
        lines.append(
            f"| **{arm}, all seeds** | - | {eps} | {_share(col, eps)} | {_share(goals, eps)} | {mean:.3f} | {rate} |"
        )
    lines += [
        "",
        "| agent | seed | collisions, filter off | collisions, filter on | goals, off | goals, on | return, off "
        "| return, on | interventions (on) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    if study.reference is not None:
        lines.append(_eval_row("goal-seeking (no learning)", "-", *study.reference))
    lines += [_eval_row(r.arm, str(r.seed), r.eval_off, r.eval_on) for r in results if r.eval_off and r.eval_on]
    for arm in arms:
        rs = [r for r in results if r.arm == arm and r.eval_off and r.eval_on]
        if rs:
            off, on = _pooled([r.eval_off for r in rs]), _pooled([r.eval_on for r in rs])
            lines.append(_eval_row(f"**{arm}, all seeds**", "-", off, on))
    return "\n".join(lines)


def load_study(record: dict[str, Any]) -> Study:
    """The :class:`Study` of a JSON record written by ``--out``."""

    def evaluation(e: dict | None) -> Evaluation | None:
        return None if e is None else Evaluation(**e)

    results = [
        ArmResult(**{**r, "eval_off": evaluation(r["eval_off"]), "eval_on": evaluation(r["eval_on"])})
        for r in record["results"]
    ]
    reference = record.get("reference")
    return Study(results, None if reference is None else (Evaluation(**reference[0]), Evaluation(**reference[1])))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (each trains every arm)")
    parser.add_argument("--steps", type=int, default=30_000, help="environment steps per agent")
    parser.add_argument("--eval-episodes", type=int, default=200, help="evaluation episodes per agent and filter")
    parser.add_argument("--eval-seed", type=int, default=10_000, help="seeds the shared evaluation starts")
    parser.add_argument("--arms", default=",".join(ARMS), help=f"which of {ARMS} to train")
    parser.add_argument("--start-margin", type=float, default=0.1, help="starts have V(x, 1.1) > this")
    parser.add_argument("--penalty", type=float, default=0.0, help="reward cost per filter intervention (shielded)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--quick", action="store_true", help="smoke run: one seed, 1,024 steps, 10 episodes")
    parser.add_argument("--out", default=None, help="also write the results as JSON here")
    parser.add_argument("--report", default=None, help="print the tables of an earlier --out JSON; train nothing")
    args = parser.parse_args(argv)
    if args.report:
        record = json.loads(Path(args.report).read_text())
        print(f"command: {record['command']}\nwall time: {record['wall_s']:.0f} s\n")
        print(tables(load_study(record)))
        return 0
    if args.quick:
        args.seeds, args.steps, args.eval_episodes = "0", 1024, 10
    torch.set_num_threads(args.threads)
    import stable_baselines3  # lazy: fail early, before any training, when the `rl` extra is missing

    seeds = [int(s) for s in args.seeds.split(",")]
    arms = args.arms.split(",")
    command = "python benchmarks/shielded_rl.py " + " ".join(argv if argv is not None else sys.argv[1:])
    print(f"command: {command.strip()}")
    print(
        f"settings: seeds {seeds}, {args.steps} env steps per agent, arms {arms}, PPO (MlpPolicy 64x64, "
        f"n_steps 512, batch 64, 10 epochs, lr 3e-4, gamma 0.99), intervention penalty {args.penalty:g}; "
        f"Air3D-v0 (pursuit policy, 1.1 s episodes, dt 0.02), starts with V(x, 1.1) > {args.start_margin:g} "
        f"of {VALUE_FUNCTION}; filter: SafetyFilterWrapper defaults (switch, greedy backup, threshold 0.06); "
        f"evaluation: {args.eval_episodes} deterministic episodes per agent, filter off and on, eval seed "
        f"{args.eval_seed}"
    )
    print(
        f"versions: torch {torch.__version__} ({torch.get_num_threads()} thread(s)), stable-baselines3 "
        f"{stable_baselines3.__version__}, gymnasium {gym.__version__}; {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores",
        flush=True,
    )

    def report(r: ArmResult) -> None:
        line = (
            f"{r.arm} seed {r.seed}: training {r.train_episodes} episodes, {r.train_collisions} collisions, "
            f"{r.train_goals} goals, mean return {r.train_mean_return:.3f}"
        )
        if r.train_intervention_rate is not None:
            line += f", interventions {r.train_intervention_rate:.1%} of steps"
        line += f" [{r.train_wall_s:.0f} s]"
        for name, e in (("off", r.eval_off), ("on", r.eval_on)):
            if e is not None:
                line += f"; eval filter {name}: {e.collisions}/{e.episodes} collisions, {e.goals} goals, "
                line += f"return {e.mean_return:.3f}"
        print(line + f" [{r.eval_wall_s:.0f} s]", flush=True)

    start = time.perf_counter()
    study = run_study(
        seeds,
        args.steps,
        args.eval_episodes,
        arms=arms,
        start_margin=args.start_margin,
        penalty=args.penalty,
        eval_seed=args.eval_seed,
        report=report,
    )
    wall = time.perf_counter() - start
    print()
    print(tables(study))
    print(f"\nwall time: {wall:.0f} s")
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        record = {
            "command": command.strip(),
            "settings": vars(args),
            "wall_s": wall,
            "results": [asdict(r) for r in study.results],
        }
        if study.reference is not None:
            record["reference"] = [asdict(e) for e in study.reference]
        out.write_text(json.dumps(record, indent=2) + "\n")
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
