"""Train until the scenario bound holds: phases of training, each verified on fresh states, whose
wrong claims become the next phase's training points.

:func:`train_until` runs one training run (:class:`training.Trainer`, in its run directory) in
phases of ``phase_steps`` steps. After each phase the network is verified
(:func:`safety.verification.verify.verify`) on fresh uniform states under the switch filter's default
backup policy for the system's kind (:data:`safety.filters.settings.DEFAULT_POLICIES`: ``"greedy"``
for avoid problems, ``"gradient"`` for reach kinds). The states it finds wrong (claimed safe, or
reachable, by ``V`` while their rollout fails) are kept as *hard states*: the next phases replace
``hard_fraction`` of every step's points by points near them (:meth:`training.sampling.PointSampler.mix_hard_states`).
Their rollouts are recorded again, and the points along each before its failure, from which the same
policy fails too, become the *refuted points*: with ``refuted_weight`` > 0 the next phases add a term
that keeps the network from claiming success there (:mod:`safety.verification.refuted`,
:class:`training.loss.RefutedPoints`). Sampling near a wrong state only applies the residual there,
which a network can meet while still claiming too much (docs/results/training.md, the quadrotor);
the refuted points say what the claim must be.
The loop stops when a phase's verification holds (wrong claims at most ``max_wrong_rate`` and a
scenario set bounded at ``target_eps``), or when the phases or the wall budget run out. Then a final
verification on states of a seed stream apart from every phase's gives the bound reported.

Files it adds to the run directory (:mod:`training.run_directory` holds the rest)::

    RUN/phases.json           the settings, every phase (steps, wall time, what its verification
                              found, hard states added) and the final verification; replaced atomically
    RUN/hard/phase-NNN.pt     the wrong states phase NNN found (read back on resume)
    RUN/hard/phase-NNN-refuted.pt  the refuted points of their rollouts: {"x": (M, n), "t": (M,)}

Every phase trains without a CUDA graph (the hard states are mixed in outside it), and the run's
stored configuration says so. Resumable: killed mid-phase, a second call continues the run from its
last checkpoint and the recorded phases (none is repeated); a call on a finished run returns its
record.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import torch

from reach.atomic import atomic_path
from reach.json_files import read_json, strict
from reach.systems import ControlAffineSystem
from safety.filters.settings import DEFAULT_POLICIES
from safety.verification.metrics import KIND_COLUMNS
from safety.verification.refuted import recorded_refuted_points
from safety.verification.rollout_store import RolloutStore
from safety.verification.verify import VerifySettings, sample_states, verify
from training import TrainConfig, Trainer
from training.loss import RefutedPoints
from training.network import NeuralValueFunction

__all__ = ["TrainUntilSettings", "final_seed", "phase_seed", "train_until"]

#: the record's file in the run directory
PHASES_FILE = "phases.json"

#: a verification uses seeds ``seed`` to ``seed + 3`` (states, delta check, robust search and check):
#: phase ``i`` takes block ``seed + 16 (i + 1)``, the final verification ``seed + 8``, apart from all
SEED_BLOCK = 16


def phase_seed(seed: int, phase: int) -> int:
    """The verification seed of phase ``phase`` (0-based)."""
    return seed + SEED_BLOCK * (phase + 1)


def final_seed(seed: int) -> int:
    """The final verification's seed: its four seeds lie between every two phases' blocks' starts, so
    no phase ever drew its states."""
    return seed + SEED_BLOCK // 2


@dataclass(frozen=True)
class TrainUntilSettings:
    """How :func:`train_until` trains and verifies; refused at construction, naming the bad value."""

    #: training steps per phase
    phase_steps: int = 2000
    #: at most this many phases
    max_phases: int = 10
    #: wall-clock budget of the phases, training and verification together, in seconds (None: phases
    #: alone); checked before each phase, so the phase under way and the final verification run past it
    budget_s: float | None = None
    #: the scenario bound to reach (the delta-level set's eps)
    target_eps: float = 3e-4
    #: the highest share of wrong claims (false safe, or false reachable) that still holds
    max_wrong_rate: float = 5e-4
    #: fresh uniform states each phase's verification rolls out
    samples: int = 100_000
    #: states of the delta-level set that check its bound (None: as many as ``samples``)
    scenario_samples: int | None = None
    #: the final verification's uniform states (None: as many as ``samples``)
    final_samples: int | None = None
    #: the verifications' seed (phase and final streams apart: :func:`phase_seed`, :func:`final_seed`)
    seed: int = 0
    #: share of every step's points drawn near the hard states
    hard_fraction: float = 0.25
    #: how near: up to this share of the box's side, per dimension
    hard_radius: float = 0.05
    #: the most recent hard states kept
    max_hard_states: int = 8192
    #: the refuted-claims term's weight (0, the default: off): each wrong state's rollout is recorded
    #: again, and the points along it before its failure, from which the same policy fails, are
    #: trained not to be claimed (:mod:`safety.verification.refuted`); each step draws
    #: ``hard_fraction`` of its point count of them. Off by default: side by side on the quadrotor it
    #: left the wrong claims on fresh states where the hard states' sampling alone did
    #: (docs/results/training.md)
    refuted_weight: float = 0.0
    #: how far past the zero level those points' claims are pushed (value units)
    refuted_margin: float = 0.0
    #: points taken along each failed rollout
    refuted_per_trajectory: int = 8
    #: the most recent refuted points kept
    max_refuted_points: int = 65536
    #: the rollouts' step (seconds), and their confidence parameter
    dt: float = 0.0025
    beta: float = 1e-16

    def __post_init__(self) -> None:
        for name in (
            "phase_steps",
            "max_phases",
            "samples",
            "max_hard_states",
            "refuted_per_trajectory",
            "max_refuted_points",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        for name in ("scenario_samples", "final_samples"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be a positive integer or None, got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        if self.budget_s is not None and not (isinstance(self.budget_s, (int, float)) and self.budget_s > 0):
            raise ValueError(f"budget_s must be a positive number of seconds or None, got {self.budget_s!r}")
        if not (isinstance(self.target_eps, (int, float)) and 0.0 < self.target_eps < 1.0):
            raise ValueError(f"target_eps must lie in (0, 1), got {self.target_eps!r}")
        if not (isinstance(self.max_wrong_rate, (int, float)) and 0.0 <= self.max_wrong_rate <= 1.0):
            raise ValueError(f"max_wrong_rate must lie in [0, 1], got {self.max_wrong_rate!r}")
        if not (isinstance(self.hard_fraction, (int, float)) and 0.0 <= self.hard_fraction < 1.0):
            raise ValueError(f"hard_fraction must lie in [0, 1), got {self.hard_fraction!r}")
        if not (isinstance(self.hard_radius, (int, float)) and 0.0 <= self.hard_radius <= 1.0):
            raise ValueError(f"hard_radius must lie in [0, 1], got {self.hard_radius!r}")
        for name in ("refuted_weight", "refuted_margin"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value < math.inf:
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        self.verify_settings(0, "avoid")  # dt and beta, checked where every verification's are

    def verify_settings(self, seed: int, kind: str, samples: int | None = None) -> VerifySettings:
        """One verification's settings: ``seed``'s stream, the default policy of ``kind``'s filter."""
        return VerifySettings(
            samples=self.samples if samples is None else samples,
            scenario_samples=self.scenario_samples,
            beta=self.beta,
            seed=seed,
            dt=self.dt,
            target_eps=self.target_eps,
            robust_samples=0,
            policy="gradient" if kind != "avoid" else DEFAULT_POLICIES["switch"],
        )


def holds(row: dict[str, Any], settings: TrainUntilSettings) -> bool:
    """Whether a verification meets the target: wrong claims at most ``max_wrong_rate`` and a scenario
    set bounded at ``target_eps``."""
    claim = KIND_COLUMNS[row["problem"]][0]
    eps = row.get("eps")
    bounded = eps is not None and math.isfinite(eps) and eps <= settings.target_eps
    return row[claim] <= settings.max_wrong_rate and bounded


def _verified(
    trainer: Trainer,
    vs: VerifySettings,
    scratch: Path,
    refuted_per_trajectory: int = 0,
    keep: int = TrainUntilSettings.max_hard_states,
) -> tuple[dict[str, Any], torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """The verification row of the trainer's network on ``vs.samples`` fresh states, the states it
    found wrong (claimed, and failed; the rollouts come back from a store, not simulated twice), and
    with ``refuted_per_trajectory`` the points along the last ``keep`` wrong states' rollouts, recorded
    again, that refute the claims (:func:`~safety.verification.refuted.recorded_refuted_points`)."""
    vf = NeuralValueFunction(trainer.network.eval())
    states = sample_states(trainer.system, vs.samples, vs.seed)
    # the rollouts go through a store: an interrupted verification resumes, and the samples' outcomes
    # come back from it, not simulated twice; removed once the row is made
    store = RolloutStore(scratch, {"seed": vs.seed, "step": trainer.step, **vs.to_dict()})
    try:
        row = verify(vf, states, vs, device=trainer.device, progress=False, store=store)
        settings = vs.rollout_settings(trainer.system.horizon)
        result = store.rollout("samples", vf, states, settings, device=trainer.device, progress=False)
    except BaseException:
        store.close()
        raise
    store.remove()
    wrong = states[((result.oriented_value > 0) & result.failed).cpu()]
    refuted = (torch.zeros(0, states.shape[1]), torch.zeros(0))
    if refuted_per_trajectory and wrong.shape[0]:
        refuted = recorded_refuted_points(vf, wrong[-keep:], settings, refuted_per_trajectory, device=trainer.device)
    trainer.network.train()
    return row, wrong, refuted


def _write(path: Path, record: dict[str, Any]) -> None:
    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        json.dump(strict(record), fh, indent=1, allow_nan=False)


def _hard_states(run: Path, phases: int, keep: int) -> torch.Tensor | None:
    parts = [torch.load(run / "hard" / f"phase-{i:03d}.pt", weights_only=True) for i in range(phases)]
    parts = [p for p in parts if p.shape[0]]
    return torch.cat(parts)[-keep:] if parts else None


def _refuted(
    run: Path, phases: int, settings: TrainUntilSettings, system: ControlAffineSystem
) -> RefutedPoints | None:
    """The refuted-claims term's points, the last ``max_refuted_points`` of every phase's, or None."""
    if settings.refuted_weight == 0:
        return None
    parts = [torch.load(run / "hard" / f"phase-{i:03d}-refuted.pt", weights_only=True) for i in range(phases)]
    parts = [p for p in parts if p["x"].shape[0]]
    if not parts:
        return None
    keep = settings.max_refuted_points
    x, t = torch.cat([p["x"] for p in parts])[-keep:], torch.cat([p["t"] for p in parts])[-keep:]
    sign = -1.0 if system.problem.reaches else 1.0
    return RefutedPoints(x, t, sign, float(settings.refuted_margin), float(settings.refuted_weight))


def _open(config: TrainConfig, run: Path, steps: int, progress: bool) -> Trainer:
    if (run / "config.json").exists():
        return Trainer.resume(run, progress=progress, steps=steps, cuda_graph=False)
    return Trainer(replace(config, steps=steps, budget_s=None, cuda_graph=False), run, progress=progress)


def train_until(
    config: TrainConfig,
    run_dir: str | Path,
    settings: TrainUntilSettings,
    progress: bool = True,
    stop_after_phases: int | None = None,
) -> dict[str, Any]:
    """Train ``config`` in ``run_dir`` phase by phase until the target holds or the budget ends
    (module docstring); returns the record written to ``RUN/phases.json``. A run directory that
    holds a record continues it (its settings must equal ``settings``), and a directory that holds a
    run continues that run under its own stored configuration (``config`` is then unused); ``stop_after_phases`` stops
    after that many phases in all, without a final verification (a later call continues)."""
    run = Path(run_dir)
    path = run / PHASES_FILE
    wanted = strict(asdict(settings))
    if path.exists():
        record = read_json(path, "train-until record")
        if recorded_settings(record.get("settings")) != wanted:
            raise ValueError(
                f"{str(path)!r} was written with other settings {record.get('settings')}; "
                "use another run directory or the same settings"
            )
        record["settings"] = wanted
    else:
        record = {"settings": wanted, "phases": [], "final": None, "stopped": None}
    if record["final"] is not None:
        return record

    def done() -> bool:
        return bool(record["phases"]) and holds(record["phases"][-1]["verification"], settings)

    while not done():
        index = len(record["phases"])
        spent = sum(p["wall_s"] for p in record["phases"])
        if index >= settings.max_phases or (settings.budget_s is not None and spent >= settings.budget_s):
            break
        if stop_after_phases is not None and index >= stop_after_phases:
            return record
        start = time.perf_counter()
        trainer = _open(config, run, settings.phase_steps * (index + 1), progress)
        trainer.sampler.hard_states = _hard_states(run, index, settings.max_hard_states)
        trainer.sampler.hard_fraction, trainer.sampler.hard_radius = settings.hard_fraction, settings.hard_radius
        trainer.sampler.refuted = _refuted(run, index, settings, trainer.system)
        trained = trainer.train()
        vs = settings.verify_settings(phase_seed(settings.seed, index), trainer.system.kind)
        per = settings.refuted_per_trajectory if settings.refuted_weight else 0
        row, wrong, (rx, rt) = _verified(trainer, vs, run / "verify-store", per, settings.max_hard_states)
        (run / "hard").mkdir(exist_ok=True)
        # both files before the record names the phase: a resumed run reads them, or reruns the phase
        with atomic_path(run / "hard" / f"phase-{index:03d}-refuted.pt") as tmp:
            torch.save({"x": rx, "t": rt}, tmp)
        with atomic_path(run / "hard" / f"phase-{index:03d}.pt") as tmp:
            torch.save(wrong, tmp)
        record["phases"].append(
            {
                "phase": index,
                "steps": trained["steps"],
                "training_wall_s": trained["wall_time_s"],
                "wall_s": time.perf_counter() - start,
                "seed": vs.seed,
                "hard_states_added": int(wrong.shape[0]),
                "refuted_points_added": int(rx.shape[0]),
                "holds": holds(row, settings),
                "verification": row,
            }
        )
        _write(path, record)
    record["stopped"] = "target" if done() else "budget"
    trainer = Trainer.resume(run, progress=False)
    vs = settings.verify_settings(final_seed(settings.seed), trainer.system.kind, settings.final_samples)
    row, _, _ = _verified(trainer, vs, run / "verify-store")
    record["final"] = {"seed": vs.seed, "steps": trainer.step, "holds": holds(row, settings), "verification": row}
    _write(path, record)
    return record


def recorded_settings(stored: object) -> object:
    """A record's settings with every field it does not hold at its default: a field added to
    :class:`TrainUntilSettings` after the record was written defaults to the loop's behaviour before
    it existed (each new field must), so an older run continues under the same settings."""
    if not isinstance(stored, dict):
        return stored
    defaults = strict(asdict(TrainUntilSettings()))
    return {**{k: v for k, v in defaults.items() if k not in stored}, **stored}


def settings_fields() -> tuple[str, ...]:
    """The names of :class:`TrainUntilSettings`' fields (the CLI's options follow them)."""
    return tuple(f.name for f in fields(TrainUntilSettings))
