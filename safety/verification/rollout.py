"""Batched closed-loop rollouts under the optimal policy of a value function, in torch.

From each initial state the engine simulates the system under ``u* = u*(x, t)`` (and the worst-case
``d*`` where the system has a disturbance) with the policy's time-to-go counting down from the
horizon, DeepReach-compatible by default: explicit Euler, ``dt = 0.0025``, headings wrapped after
every step, collision = some visited state with ``l(x) <= 0``. ``integrator="rk4"`` holds the inputs
of a step constant and integrates the dynamics with RK4 instead.

The outcome follows the system's kind (:mod:`reach.systems.problem`). Avoid: the rollout *fails*
when it collides. Reach and reach-avoid: the control minimises ``V`` and the rollout *succeeds* when
it reaches the target (``l(x) <= 0``, target margin) before the horizon without first leaving the
constraint set (``g(x) <= 0`` is a collision, reach-avoid only; a state in both counts as a
collision, as in the grid's ``max(min(V, l), -g)``). Either outcome ends the trajectory. The
dynamics hold beyond the domain, so a trajectory that leaves it and comes back to the target in
time has succeeded: the value function is read out there as for avoid problems (a grid solution
refuses unless it was loaded with ``outside="clamp"``, as ``reach evaluate`` does).

It simulates only what is still undecided:

* a trajectory that has collided (or, for reach kinds, reached the target) is finished, and states
  already in collision (or in the target) never start;
* where the system bounds how fast ``l`` can fall
  (:meth:`~reach.systems.base.ControlAffineSystem.margin_floor`: by default
  ``l(x) - c * time`` from a declared ``|dl/dt| <= c``; multi-vehicle systems also use the cars'
  headings, since cars facing apart must turn before they can close), a trajectory whose floor over
  ``time_left + dt`` is positive can no longer reach the failure set under *any* inputs, so its
  outcome (no collision) is decided and it stops too. Exact for Euler (a held step moves ``l`` by
  at most what the floor allows); the extra ``dt`` covers RK4's truncation;
* for reach kinds, where the system bounds how fast the target margin can fall
  (:meth:`~reach.systems.base.ControlAffineSystem.target_floor`), a trajectory whose target floor
  over ``time_left + dt`` is positive can no longer reach the target in time: it has failed, and it
  stops. A reach-avoid trajectory stops so only where its constraint is out of reach too
  (:meth:`~reach.systems.base.ControlAffineSystem.margin_floor` of the constraint margin), so the
  violations counted are those a full simulation finds.

A value function that returns NaN or inf (its value at a start, its gradient along the way) or a
state that turns non-finite stops the rollout with a ``ValueError`` naming the state and its row: a NaN gradient
would still pick some input, not the value's policy, and a NaN state never meets the failure set.

States go through in chunks (bounded memory), the network runs without an autograd graph (one
fused value-and-gradient pass per state and step, see ``ValueNetwork.value_and_gradient``), and a
progress bar counts chunk-steps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import torch
from tqdm.auto import tqdm

from reach.integrators import check_integrator, make_stepper
from reach.systems import ControlAffineSystem
from reach.systems.arrays import TORCH
from reach.systems.box import project_inputs
from reach.systems.problem import problem_kind
from reach.validation import check_int, positive_finite, settings_from
from reach.value_function import ValueFunction, check_time_coverage
from safety.value_policies import GreedyPolicy, check_policy, check_states

DisturbanceSpec = Literal["optimal", "none"] | Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class RolloutResult:
    """Outcome per initial state, and what it cost.

    Attributes:
        initial_value: ``V(x0, T)`` from the same value function.
        collided: the trajectory visited a state with ``l(x) <= 0`` (including ``x0``): the failure
            set (avoid) or outside the constraint set (reach-avoid; never for reach).
        collision_time: first time with ``l <= 0`` (0 for states starting in collision; NaN if none).
        decided_time: when the outcome was settled: the collision time, the time the margin bound
            ruled collision out, or the horizon.
        state_steps: value-gradient evaluations done (the work; ``N x steps`` without early exits).
        steps: steps of the full horizon.
        wall_time: seconds.
        trajectories: ``(steps + 1, N, n)`` states when ``record=True`` (frozen once decided).
        kind: the system's kind of problem (``"avoid"``, ``"reach"`` or ``"reach-avoid"``).
        reached: reach kinds: the trajectory reached the target before the horizon without a
            collision first (None for avoid).
        reach_time: reach kinds: when it reached the target (NaN if it did not).
    """

    initial_value: torch.Tensor
    collided: torch.Tensor
    collision_time: torch.Tensor
    decided_time: torch.Tensor
    state_steps: int
    steps: int
    wall_time: float
    trajectories: torch.Tensor | None = field(default=None, repr=False)
    kind: str = "avoid"
    reached: torch.Tensor | None = None
    reach_time: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if problem_kind(self.kind, "rollout result").reaches and (self.reached is None or self.reach_time is None):
            raise ValueError(f"a {self.kind} rollout result needs reached and reach_time")

    @property
    def num_states(self) -> int:
        return int(self.collided.numel())

    @property
    def failed(self) -> torch.Tensor:
        """Per state, whether the rollout failed its task: collided (avoid), or did not reach the
        target in time without a collision (reach kinds)."""
        return self.collided if self.reached is None else ~self.reached

    @property
    def oriented_value(self) -> torch.Tensor:
        """``V(x0, T)`` turned so that ``> 0`` is the value function's claim (safe, or reachable):
        :meth:`~reach.systems.problem.ProblemKind.orient`."""
        return problem_kind(self.kind).orient(self.initial_value)

    @property
    def work_fraction(self) -> float:
        """Evaluations done relative to simulating every state for every step."""
        return self.state_steps / max(1, self.num_states * self.steps)


def num_steps(horizon: float, dt: float) -> int:
    """``ceil(horizon / dt)``, robust to round-off (1 / 0.0025 gives 400)."""
    return max(1, math.ceil(horizon / dt - 1e-9))


@dataclass(frozen=True)
class RolloutSettings:
    """How a rollout simulates: validated once here, passed whole (``rollout(vf, x, settings)``).

    Attributes:
        horizon: time-to-go at the start (None: the system's horizon).
        dt: step length in seconds; a positive finite real no longer than the horizon.
        integrator: ``"euler"`` (DeepReach's) or ``"rk4"`` (inputs held over the step).
        policy: ``"gradient"`` (the bang-bang ``u*`` of ``grad V``) or ``"greedy"``
            (:class:`~safety.value_policies.GreedyPolicy`: the candidate input held for
            :data:`~safety.value_policies.GREEDY_STEP` that leaves the most value; about ``2^m_u + 1``
            times the network work per step). The disturbance is the gradient's ``d*`` either way.
        chunk_size: states simulated together (memory is about ``chunk_size x width x layers``).
        matmul_precision: ``"bfloat16"`` runs a network's hidden products in bfloat16 (neural value
            functions only): faster on CPUs and GPUs with bf16 units, and not exact: outcomes can
            differ from float32 near the BRT boundary (measured: docs/results/verification.md,
            *Rollout engine*).
        early_exit: stop trajectories whose outcome is decided (see the module docstring).
        control_period: how often the policy decides, in seconds: its input is held in between, as
            a controller acting every ``control_period`` holds it (a whole multiple of ``dt``; None:
            every step). The disturbance still acts at every step. A greedy policy held for its own
            lookahead (:data:`~safety.value_policies.GREEDY_STEP`) applies each input exactly as long
            as it looked ahead, at a fraction of the cost.

    Every field is checked at construction and a bad one raises ``ValueError`` naming it; NumPy and
    0-d tensor reals are taken (and stored as Python numbers).
    """

    horizon: float | None = None
    dt: float = 0.0025
    integrator: str = "euler"
    policy: str = "gradient"
    chunk_size: int = 16384
    matmul_precision: str = "float32"
    early_exit: bool = True
    control_period: float | None = None

    def __post_init__(self) -> None:
        horizon = None if self.horizon is None else positive_finite("horizon", self.horizon)
        dt = positive_finite("dt", self.dt)
        if horizon is not None and dt > horizon:
            raise ValueError(f"dt must not exceed the horizon: dt {dt:g} s is longer than the horizon {horizon:g} s")
        check_integrator(self.integrator)
        check_policy(self.policy)
        if self.matmul_precision not in ("float32", "bfloat16"):
            raise ValueError(f"matmul_precision must be 'float32' or 'bfloat16', got {self.matmul_precision!r}")
        if not isinstance(self.early_exit, bool):
            raise ValueError(f"early_exit must be True or False, got {self.early_exit!r}")
        if self.control_period is not None:
            period = positive_finite("control_period", self.control_period)
            if abs(period / dt - round(period / dt)) > 1e-6 or round(period / dt) < 1:
                raise ValueError(f"control_period must be a whole multiple of dt ({dt:g} s), got {period:g} s")
            object.__setattr__(self, "control_period", period)
        object.__setattr__(self, "horizon", horizon)
        object.__setattr__(self, "dt", dt)
        object.__setattr__(self, "chunk_size", check_int("chunk_size", self.chunk_size, 1))

    @classmethod
    def of(cls, settings: RolloutSettings | None, keywords: dict[str, Any]) -> RolloutSettings:
        """``settings`` with ``keywords`` (field names) replaced, or the defaults with them: the one
        place where a rollout's keyword arguments become settings (:func:`reach.validation.settings_from`)."""
        return settings_from(cls, settings, keywords, "rollout")

    def for_system(self, system: ControlAffineSystem) -> RolloutSettings:
        """These settings with the horizon resolved to the system's where it is None (checked again:
        a step longer than the system's horizon is refused)."""
        return self if self.horizon is not None else replace(self, horizon=system.horizon)


#: states a CUDA device rolls out at once by default (:func:`default_chunk_size`). The CPU default
#: (``RolloutSettings.chunk_size``) left a GPU launch-bound (measured: docs/results/benchmarks.md,
#: *On a GPU*).
CUDA_CHUNK_SIZE = 262_144


def default_chunk_size(device: str | torch.device) -> int:
    """The chunk size for rollouts on ``device`` when the user names none: ``RolloutSettings``' default
    on a CPU (or any other device), :data:`CUDA_CHUNK_SIZE` on a CUDA GPU, which only fills up with
    larger blocks. ``reach evaluate`` uses it; the chosen size is recorded with each row's settings."""
    if torch.device(device).type == "cuda":
        return CUDA_CHUNK_SIZE
    return RolloutSettings.chunk_size


def concat_results(parts: list[RolloutResult]) -> RolloutResult:
    """The results of consecutive blocks of one batch of states as one result: outcomes in block
    order; ``state_steps`` and ``wall_time`` summed (each block's own simulation, wherever it ran)."""
    kind = parts[0].kind
    reach = kind != "avoid"
    return RolloutResult(
        initial_value=torch.cat([p.initial_value for p in parts]),
        collided=torch.cat([p.collided for p in parts]),
        collision_time=torch.cat([p.collision_time for p in parts]),
        decided_time=torch.cat([p.decided_time for p in parts]),
        state_steps=sum(p.state_steps for p in parts),
        steps=parts[0].steps,
        wall_time=sum(p.wall_time for p in parts),
        kind=kind,
        reached=torch.cat([p.reached for p in parts]) if reach else None,
        reach_time=torch.cat([p.reach_time for p in parts]) if reach else None,
    )


def check_admissible(d: Any, system: ControlAffineSystem) -> Any:
    """``d`` as given if it lies in the system's disturbance bounds (to rounding), else ``ValueError``
    naming a value outside: a rollout's outcomes, and its early exits' floors, hold for admissible
    disturbances only. Anything but a ``(..., m_d)`` tensor passes on to the input checks."""
    bounds = system.disturbance_bounds
    if not isinstance(d, torch.Tensor) or d.shape[-1:] != (bounds.dim,) or not d.dtype.is_floating_point:
        return d
    tol = 1e-6 * (1.0 + max(bounds.half_width))
    excess = torch.linalg.vector_norm(d - project_inputs(d, bounds), dim=-1)  # distance to the set
    bad = ~(excess <= tol)  # NaN counts as outside
    if bool(bad.any()):
        value = d[bad][0].tolist()
        raise ValueError(f"the disturbance function returned {value}, outside the system's disturbance bounds {bounds}")
    return d


def refuse_non_finite(
    values: torch.Tensor, states: torch.Tensor, index: torch.Tensor, what: str, time_to_go: float
) -> None:
    """Raise ``ValueError`` naming the first state whose row of ``values`` holds NaN or inf: the state
    itself (``states``, the rows ``values`` were computed at) and its row in the rollout's batch
    (``index``), which a caller that splits its states into blocks numbers from each block's start.

    A rollout cannot judge a value function where it is not finite: a NaN gradient still picks some
    input (an arbitrary one, not the value's policy), and a state that turned NaN never meets the
    failure set, so an avoid rollout would count it safe."""
    bad = ~torch.isfinite(values.reshape(values.shape[0], -1)).all(dim=-1)
    if bool(bad.any()):
        first = int(bad.nonzero()[0, 0])
        state = [float(f"{v:.6g}") for v in states[first].tolist()]
        raise ValueError(
            f"rollout: {what} is not finite at the state {state} (row {int(index[first])} of the batch) at "
            f"time-to-go {time_to_go:g}; a rollout refuses a value function it cannot trust rather than "
            "judging another policy"
        )


def rollout(
    value_function: ValueFunction,
    states: torch.Tensor,
    settings: RolloutSettings | None = None,
    *,
    disturbance: DisturbanceSpec = "optimal",
    record: bool = False,
    device: str | torch.device | None = None,
    dtype: torch.dtype = torch.float32,
    progress: bool = True,
    **keywords: Any,
) -> RolloutResult:
    """Roll out every state in ``states`` ``(N, n)`` under the value function's induced policy.

    Args:
        settings: how to simulate (:class:`RolloutSettings`: horizon, step, integrator, policy,
            batch size, precision, early exit); its fields may also be given as keywords
            (``rollout(vf, x, dt=0.01, policy="greedy")``), alone or over ``settings``.
        disturbance: ``"optimal"`` (worst case ``d*``), ``"none"`` (box centre) or ``fn(x, t) -> d``,
            which must stay within the disturbance bounds (a value outside raises ``ValueError``).
        record: keep every state (small ``N`` only; turns the margin-bound exit off).
        device: where to simulate (default: the states' device).
        dtype: precision of the simulation (default float32).
        progress: show a progress bar over chunk-steps.
    """
    settings = RolloutSettings.of(settings, keywords).for_system(value_function.system)
    horizon, dt, integrator, policy = settings.horizon, settings.dt, settings.integrator, settings.policy
    chunk_size, matmul_precision, early_exit = settings.chunk_size, settings.matmul_precision, settings.early_exit
    system = value_function.system
    check_states(states, system.state_dim)
    if states.ndim != 2:
        raise ValueError(f"states must have shape (N, {system.state_dim}), got {tuple(states.shape)}")
    if not (disturbance in ("optimal", "none") or callable(disturbance)):
        raise ValueError(f"disturbance must be 'optimal', 'none' or a callable, got {disturbance!r}")
    check_time_coverage(value_function, 0.0, horizon, f"a rollout from time-to-go {horizon:g}")
    if matmul_precision == "bfloat16":
        if not hasattr(value_function, "with_matmul_dtype"):
            kind = type(value_function).__name__
            raise ValueError(f"matmul_precision='bfloat16' needs a neural value function, not {kind}")
        value_function = value_function.with_matmul_dtype(torch.bfloat16)
    device = torch.device(device) if device is not None else states.device
    n_steps = num_steps(horizon, dt)
    if record and states.shape[0] > 100_000:
        raise ValueError(f"record=True keeps every state; {states.shape[0]} states is too many (<= 100000)")
    problem = system.problem
    floor_exit = early_exit and not record and not problem.reaches
    target_exit = early_exit and not record and problem.reaches
    # what ends a trajectory in failure: the failure set (avoid), leaving the constraint set (reach-avoid)
    collision_margin = None if problem.name == "reach" else system.failure_margin
    use_disturbance = system.disturbance_dim > 0 and disturbance != "none"

    advance = make_stepper(system, dt, integrator, TORCH)
    greedy = GreedyPolicy(value_function, dt=dt, integrator=integrator) if policy == "greedy" else None

    hold = None if settings.control_period is None else round(settings.control_period / dt)

    def step(
        x: torch.Tensor, t: float, held: torch.Tensor | None, idx: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The next states, and the inputs applied: ``held`` where given, else the policy's now. A
        non-finite gradient, input or next state is refused (:func:`refuse_non_finite`)."""
        # the gradient where u* or d* needs it: networks fuse it with the value; grids interpolate it alone
        wants_p = (greedy is None and held is None) or (disturbance == "optimal" and use_disturbance)
        p = value_function.gradient(x, t) if wants_p else None
        if p is not None:
            refuse_non_finite(p, x, idx, "the value function's gradient", t)
        if not use_disturbance:
            d = None
        elif disturbance == "optimal":
            d = system.optimal_disturbance(x, p)
        else:
            d = check_admissible(disturbance(x, torch.full(x.shape[:-1], t, dtype=x.dtype, device=x.device)), system)
        u = held
        if u is None:
            u = system.optimal_control(x, p) if greedy is None else greedy.control(x, t, d)
            refuse_non_finite(u, x, idx, "the policy's input", t)
        cols = TORCH.unbind(x)
        uc = system.input_columns(u, system.control_bounds, "u")
        dc = system.input_columns(d, system.disturbance_bounds, "d")
        x_next = TORCH.stack(advance(cols, uc, dc), like=cols[0])  # integrates and wraps headings
        refuse_non_finite(x_next, x, idx, "the next state from", t)
        return x_next, u

    n = states.shape[0]
    initial_value = torch.empty(n, dtype=dtype)
    collided = torch.zeros(n, dtype=torch.bool)
    collision_time = torch.full((n,), math.nan, dtype=torch.float64)
    decided_time = torch.full((n,), horizon, dtype=torch.float64)
    reached = torch.zeros(n, dtype=torch.bool) if problem.reaches else None
    reach_time = torch.full((n,), math.nan, dtype=torch.float64) if problem.reaches else None

    def outcomes(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Per state: collided (constraint or failure set) and, for reach kinds, in the target first."""
        nothing = torch.zeros_like(x[..., 0], dtype=torch.bool)
        hit = nothing if collision_margin is None else collision_margin(x) <= 0
        return hit, (system.target_margin(x) <= 0) & ~hit if problem.reaches else None

    def out_of_reach(x: torch.Tensor, time: float) -> torch.Tensor | None:
        """Per state, whether no input reaches the target within ``time`` (and, for reach-avoid, none
        leaves the constraint set either, so the violations counted stay the same): a failure.
        ``None`` where the system bounds neither (as :meth:`margin_floor` answers)."""
        target = system.target_floor(x, time)
        if target is None or not problem.has_constraint:
            return None if target is None else target > 0
        floor = system.margin_floor(x, time)
        return None if floor is None else (target > 0) & (floor > 0)

    def settle(where_hit: torch.Tensor, where_reached: torch.Tensor | None, at: float) -> None:
        """Record the trajectories decided at time ``at`` (global indices on the CPU)."""
        collided[where_hit] = True
        collision_time[where_hit] = at
        decided_time[where_hit] = at
        if where_reached is not None and where_reached.numel():
            reached[where_reached] = True
            reach_time[where_reached] = at
            decided_time[where_reached] = at

    trajectories = torch.empty((n_steps + 1, n, system.state_dim), dtype=dtype) if record else None
    state_steps = 0
    chunks = list(range(0, n, chunk_size))
    start = time.perf_counter()
    with (
        torch.no_grad(),
        tqdm(
            total=len(chunks) * n_steps, desc="rollouts", unit="step", **({} if progress else {"disable": True})
        ) as bar,
    ):
        for lo in chunks:
            hi = min(lo + chunk_size, n)
            x = states[lo:hi].to(device=device, dtype=dtype)
            idx = torch.arange(lo, hi, device=device)
            v0 = value_function.value(x, horizon)
            refuse_non_finite(v0, x, idx, "the value function's value", horizon)
            initial_value[lo:hi] = v0.to(dtype).cpu()
            hit0, in_target = outcomes(x)
            done0 = hit0 if in_target is None else hit0 | in_target
            if record:
                trajectories[0, lo:hi] = x.cpu()
            if bool(done0.any()):
                settle(idx[hit0].cpu(), None if in_target is None else idx[in_target].cpu(), 0.0)
                x, idx = x[~done0], idx[~done0]
            held = None  # the inputs being held (a control period longer than dt)
            for k in range(n_steps):
                if idx.numel() == 0:
                    bar.update(n_steps - k)
                    break
                t_go = max(horizon - k * dt, 0.0)
                x, u = step(x, t_go, None if hold is None or k % hold == 0 else held, idx)
                held = None if hold is None else u
                state_steps += int(idx.numel())
                elapsed = min((k + 1) * dt, horizon)
                if record:
                    trajectories[k + 1, lo:hi] = trajectories[k, lo:hi]
                    trajectories[k + 1, idx.cpu()] = x.cpu()
                hit, in_target = outcomes(x)
                done = hit if in_target is None else hit | in_target
                floor = system.margin_floor(x, horizon - elapsed + dt) if floor_exit else None
                if floor is not None:
                    done = done | (floor > 0)
                stopped = out_of_reach(x, horizon - elapsed + dt) if target_exit else None
                if stopped is not None:
                    done = done | stopped
                if bool(done.any()):
                    settle(idx[hit].cpu(), None if in_target is None else idx[in_target].cpu(), elapsed)
                    # the floor exits: avoid's (no collision any more), reach's (no target any more)
                    exited = done & ~hit if in_target is None else done & ~hit & ~in_target
                    if bool(exited.any()):
                        decided_time[idx[exited].cpu()] = elapsed
                    keep = ~done
                    x, idx = x[keep], idx[keep]
                    held = None if held is None else held[keep]
                bar.update(1)
    return RolloutResult(
        initial_value=initial_value,
        collided=collided,
        collision_time=collision_time,
        decided_time=decided_time,
        state_steps=state_steps,
        steps=n_steps,
        wall_time=time.perf_counter() - start,
        trajectories=trajectories,
        kind=problem.name,
        reached=reached,
        reach_time=reach_time,
    )
