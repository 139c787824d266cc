"""The training loop: sampling, curriculum, Adam, stop rules, checkpoints, metrics, resume.

A run is a directory::

    RUN/config.json        resolved TrainConfig
    RUN/checkpoint.pt      latest good state (network, optimizer, RNG, step, wall time)
    RUN/checkpoint.json    its metadata (system, layout, width, encoding, steps, versions, ...)
    RUN/metrics.jsonl      one JSON line per logged step (loss terms, lr, steps/s, evaluations)
    RUN/tensorboard/       with ``tensorboard = True``: the same metrics as TensorBoard scalars
    RUN/snapshots/NNN.pt   with ``snapshots = K``: the network after each K-th of the run (+ .json),
                           for accuracy-versus-time studies that evaluate after training

Checkpoint files are replaced atomically; metrics lines are appended and flushed, and on resume any
line past the checkpoint's step (or torn by a kill) is dropped, so a killed run resumes exactly
where its last checkpoint stood and its metrics continue without duplicates.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from reach.atomic import atomic_path
from reach.locking import run_lock
from reach.threads import thread_policy
from reach.validation import check_output_dir
from training.checkpoint import network_from_payload, read_checkpoint, save_checkpoint
from training.config import TrainConfig
from training.labels import check_lower_bound_system, mpc_lower_bound, policy_lower_bound
from training.loss import residual_function, training_loss
from training.network import Encoding, NeuralValueFunction, ValueNetwork

#: values for keys that a stored config.json predates: the behaviour such runs were trained with
#: (resuming them must not switch on a later default such as the gradient bound)
LEGACY_DEFAULTS: dict[str, Any] = {"gradient_bound": None, "sincos_radius": 1.0}


#: files whose presence means a directory already holds a run
RUN_FILES = ("config.json", "checkpoint.pt", "metrics.jsonl")

#: what ``resume`` may change: stop rules, logging and the device; anything else would make the
#: resumed run a different run than its checkpoint and metrics say
RESUME_OVERRIDABLE = frozenset(
    {"steps", "budget_s", "target_loss", "device", "log_every", "checkpoint_every_s", "eval_every_s", "tensorboard"}
)


def moved_run_seed(seed: int, step: int) -> int:
    """The sampling generator's seed for a run resumed on another kind of device at ``step``: a CPU
    generator's state cannot seed a CUDA one or back, so the stream restarts from the run's seed and
    step (deterministic: two resumes of the same checkpoint on the same device draw the same points)."""
    return (seed * 1_000_003 + step) % (2**63)


class TrainingDivergedError(RuntimeError):
    """The loss became NaN or inf; the last good checkpoint is kept."""


class TrainingInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM stopped the run; it was checkpointed first, so ``resume`` loses nothing."""


Evaluator = Callable[[NeuralValueFunction], dict[str, float]]


@contextlib.contextmanager
def _deferred_signals() -> Iterator[dict[str, int]]:
    """Catch SIGINT and SIGTERM for the ``with`` block: the yielded dict gets ``{"signal": n}`` and
    the loop stops at the end of its step. A second signal of the same kind acts as usual (a user who
    presses Ctrl-C twice means it). Only the main thread can install handlers; elsewhere this is a no-op."""
    stop: dict[str, int] = {}
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum: int, frame: Any) -> None:
        if stop:  # second signal: restore and re-deliver
            signal.signal(signum, previous[signum])
            signal.raise_signal(signum)
            return
        stop["signal"] = signum

    for sig in previous:
        signal.signal(sig, handler)
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def build_network(config: TrainConfig) -> ValueNetwork:
    """The run's network, initialised from ``config.seed`` alone (not from the global RNG's state, which
    depends on what the process did before: runs of one sweep in one process would differ from the
    same runs in fresh processes)."""
    system = config.build_system()
    encoding = Encoding.for_system(
        system, sincos=config.sincos, value_scale=config.value_scale, sincos_radius=config.sincos_radius
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        return ValueNetwork(system, config.layout, config.width, config.parameterisation, config.w0, encoding)


def _clean_metrics(path: Path, last_step: int) -> None:
    """Keep only whole metric lines up to ``last_step`` (drops a torn tail after a kill)."""
    if not path.exists():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            break
        if row.get("step", math.inf) > last_step:
            break
        kept.append(line)
    with atomic_path(path) as tmp:
        Path(tmp).write_text("".join(f"{line}\n" for line in kept))


def _upper_bound(config: TrainConfig, system: Any) -> Any:
    """The union of pairwise BRTs that ``config.upper_bound`` names, loaded (and refused) before training."""
    if config.upper_bound is None:
        return None
    from groundtruth.pairwise import PairwiseUnion
    from reach.systems import MultiVehicle

    if not isinstance(system, MultiVehicle):
        raise ValueError(f"upper_bound: a pairwise union bounds multi-vehicle systems only, not {system.name}")
    if not Path(config.upper_bound).is_file():
        raise ValueError(f"upper_bound: no such file {config.upper_bound!r}")
    union = PairwiseUnion.load(system, config.upper_bound)
    if union.system.horizon < system.horizon:
        raise ValueError(
            f"upper_bound {config.upper_bound}: its pair solution reaches t = {union.system.horizon:g}, "
            f"the system's horizon is {system.horizon:g}"
        )
    return union


class Trainer:
    """Runs one training run in ``run_dir`` (see the module docstring)."""

    def __init__(
        self,
        config: TrainConfig,
        run_dir: str | os.PathLike,
        evaluator: Evaluator | None = None,
        progress: bool = True,
        *,
        _resuming: bool = False,
    ) -> None:
        self.config = config.validate()
        self.run_dir = Path(run_dir)
        if not _resuming:
            check_output_dir(self.run_dir, "run")
            existing = [name for name in RUN_FILES if (self.run_dir / name).exists()]
            if existing:
                raise ValueError(
                    f"{self.run_dir} already holds a run ({', '.join(existing)}); continue it with "
                    f"`reach train --resume {self.run_dir}` (Trainer.resume) or choose another directory"
                )
        if evaluator is not None and getattr(evaluator, "system", None) is not None:
            wanted = config.build_system()
            wanted.require_same_physics(evaluator.system, "the evaluation ground truth")
        self.evaluator = evaluator
        self.progress = progress
        self.device = torch.device(config.device)
        self.network = build_network(config).to(self.device)
        self.system = self.network.system
        self.optimizer = torch.optim.Adam(self.network.parameters(), lr=config.lr)
        self.residual_fn = residual_function(self.network, config.gradients, config.compile_resolved())
        #: the gradient bound in the network's normalised coordinates (``gradient_bound`` x l's steepest slope)
        self.gradient_bound = (
            None if config.gradient_bound is None else config.gradient_bound * self.network.margin_slope()
        )
        self.upper_bound = _upper_bound(config, self.system)
        if config.lower_bound is not None:
            check_lower_bound_system(self.system)
        #: the labelled points (x, t, J) of the lower-bound term, refreshed every lower_bound_every steps
        self.labels: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self.step = 0
        self.wall = 0.0  # seconds of training, accumulated across resumes
        self.loss_ema: float | None = None
        box = self.system.domain_tensor(torch.float32, self.device)
        self._low, self._span = box[:, 0], box[:, 1] - box[:, 0]

    def _uniform(self, n: int, tmax: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` states uniform on the domain and times uniform on ``[0, tmax]``, from the run's generator
        (states first: resumed runs replay the same stream)."""
        g = self.generator
        x = self._low + torch.rand((n, self.system.state_dim), generator=g, device=self.device) * self._span
        return x, torch.rand(n, generator=g, device=self.device) * tmax

    def _refresh_labels(self, tmax: float) -> None:
        """Label fresh states with what the network's policy achieves (``J <= V``), every
        ``lower_bound_every`` steps (and at the start of a run that has none)."""
        c = self.config
        if c.lower_bound is None or tmax <= 0:
            return
        if self.labels is not None and self.step % c.lower_bound_every:
            return
        n, g = c.lower_bound_points, self.generator
        x, t = self._uniform(n, tmax)
        if c.lower_bound == "mpc":
            floor = mpc_lower_bound(
                self.network,
                x,
                t,
                c.lower_bound_dt,
                c.lower_bound_horizon,
                c.lower_bound_samples,
                c.lower_bound_noise,
                g,
            )
        else:
            floor = policy_lower_bound(self.network, x, t, c.lower_bound_dt)
        self.labels = (x, t, floor)

    def _upper_bound_at(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The union's value at the sampled points (``+inf`` where no pair grid covers them)."""
        with torch.no_grad():  # the pair grids interpolate on the points' own device
            return self.upper_bound.value_where_known(x.detach(), t.detach()).to(x.dtype)

    # ------------------------------------------------------------------ persistence
    @property
    def checkpoint_path(self) -> Path:
        return self.run_dir / "checkpoint.pt"

    def _save(self) -> None:
        extra = {
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "step": self.step,
            "wall": self.wall,
            "loss_ema": self.loss_ema,
            "labels": self.labels,
        }
        meta = {
            "steps": self.step,
            "wall_time_s": self.wall,
            "seed": self.config.seed,
            "config": json.loads(self.config.to_json()),
        }
        save_checkpoint(self.checkpoint_path, self.network, extra, meta)

    @classmethod
    def resume(
        cls, run_dir: str | os.PathLike, evaluator: Evaluator | None = None, progress: bool = True, **overrides: Any
    ) -> Trainer:
        """Continue the run in ``run_dir``; ``overrides`` may extend stop rules (steps, budget_s, ...)."""
        run_dir = Path(run_dir)
        cfg_path = run_dir / "config.json"
        if not cfg_path.exists():
            raise ValueError(f"{run_dir}: no config.json; not a training run directory")
        try:
            data = {**LEGACY_DEFAULTS, **json.loads(cfg_path.read_text())}
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"{cfg_path}: unreadable run configuration ({err})") from err
        given = {k: v for k, v in overrides.items() if v is not None}
        fixed = {k: v for k, v in given.items() if k not in RESUME_OVERRIDABLE and data.get(k) != v}
        if fixed:
            stored = ", ".join(f"{k}={data.get(k)!r}" for k in sorted(fixed))
            raise ValueError(
                f"{run_dir} was trained with {stored}; a resumed run keeps its configuration (only "
                f"{', '.join(sorted(RESUME_OVERRIDABLE))} may change): start a new run to change {sorted(fixed)}"
            )
        trained_on = torch.device(str(data.get("device") or "cpu")).type
        data.update(given)
        trainer = cls(TrainConfig.from_dict(data), run_dir, evaluator, progress, _resuming=True)
        if trainer.checkpoint_path.exists():
            payload = read_checkpoint(trainer.checkpoint_path)
            net = network_from_payload(
                trainer.checkpoint_path, payload, system=trainer.system, layout=trainer.config.layout
            )
            if net.architecture() != trainer.network.architecture():
                raise ValueError(
                    f"{trainer.checkpoint_path}: network {net.architecture()} does not match the run's "
                    f"config.json, which builds {trainer.network.architecture()}"
                )
            trainer.network.load_state_dict(net.state_dict())
            trainer.optimizer.load_state_dict(payload["optimizer"])
            trainer.step, trainer.wall, trainer.loss_ema = payload["step"], payload["wall"], payload["loss_ema"]
            if trained_on == trainer.device.type:
                trainer.generator.set_state(payload["generator"])
            else:  # a CPU and a CUDA generator have different states: the stream cannot carry over
                trainer.generator.manual_seed(moved_run_seed(trainer.config.seed, trainer.step))
                warnings.warn(
                    f"{run_dir}: trained on {trained_on}, resumed on {trainer.device.type} at step {trainer.step}: "
                    "the sampling generator is reseeded from the run's seed and step (same schedule and "
                    "steps, not the sample stream of an uninterrupted run on one device)",
                    stacklevel=2,
                )
            labels = payload.get("labels")  # checkpoints load on the CPU; the labels train on the run's device
            trainer.labels = None if labels is None else tuple(v.to(trainer.device) for v in labels)
        _clean_metrics(run_dir / "metrics.jsonl", trainer.step)
        return trainer

    @property
    def snapshot_dir(self) -> Path:
        return self.run_dir / "snapshots"

    def _snapshot(self, index: int) -> None:
        """Save the network alone as snapshot ``index`` (of ``config.snapshots``), with its step and wall time."""
        meta = {
            "steps": self.step,
            "wall_time_s": self.wall,
            "fraction": self.progress_fraction(),
            "snapshot": index,
            "snapshots": self.config.snapshots,
            "seed": self.config.seed,
            "config": json.loads(self.config.to_json()),
        }
        self.snapshot_dir.mkdir(parents=True, exist_ok=True)
        save_checkpoint(self.snapshot_dir / f"{index:03d}.pt", self.network, None, meta)

    def _snapshots_due(self) -> int:
        """How many snapshots the run's progress calls for (0 .. ``config.snapshots``)."""
        k = self.config.snapshots
        return min(k, int(self.progress_fraction() * k + 1e-9))

    @classmethod
    def open(cls, config: TrainConfig, run_dir: str | os.PathLike, progress: bool = True) -> Trainer:
        """The run in ``run_dir``: resumed (its stored configuration rules) if it exists, else a new
        run of ``config``. Callers that must not adopt another configuration compare ``.config``."""
        run_dir = Path(run_dir)
        if (run_dir / "config.json").exists():
            return cls.resume(run_dir, progress=progress)
        return cls(config, run_dir, progress=progress)

    def needs_training(self) -> bool:
        """Whether :meth:`train` has work left: no stop rule holds yet, or nothing was saved."""
        return self.stop_reason() is None or not self.checkpoint_path.exists()

    # ------------------------------------------------------------------ schedule
    def progress_fraction(self) -> float:
        """How far the run is, in [0, 1], by its step or time budget (whichever is further)."""
        c = self.config
        parts = []
        if c.steps is not None:
            parts.append(self.step / c.steps)
        if c.budget_s is not None:
            parts.append(self.wall / c.budget_s)
        return min(1.0, max(parts)) if parts else 0.0

    def learning_rate(self, frac: float) -> float:
        c = self.config
        if c.schedule == "constant":
            return c.lr
        return c.lr_final + 0.5 * (c.lr - c.lr_final) * (1 + math.cos(math.pi * frac))

    def time_range(self, frac: float) -> float:
        c = self.config
        if c.curriculum <= 0:
            return self.system.horizon
        pre = c.pretrain if c.parameterisation == "vanilla" else 0.0
        grow = (frac - pre) / c.curriculum if frac > pre else 0.0
        return self.system.horizon * min(1.0, max(0.0, grow))

    def _sample(self, tmax: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        c = self.config
        n = c.points
        x, t = self._uniform(n, tmax)
        mask = None
        if c.parameterisation == "vanilla":
            mask = torch.zeros(n, dtype=torch.bool, device=self.device)
            mask[: int(c.boundary_fraction * n)] = True
            t = torch.where(mask, torch.zeros_like(t), t)
        near = int(c.zero_level_fraction * n)
        if near:  # the last points (never the vanilla boundary's first ones): nearest V = 0 of a larger draw
            x[n - near :], t[n - near :] = self._near_zero_level(near, tmax)
        return x, t, mask

    def _near_zero_level(self, count: int, tmax: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` states and times with the smallest ``|V|`` among ``zero_level_candidates x count``
        uniform draws (one forward pass without gradients)."""
        m = count * self.config.zero_level_candidates
        x, t = self._uniform(m, tmax)
        with torch.no_grad():
            keep = self.network(x, t).abs().topk(count, largest=False).indices
        return x[keep], t[keep]

    def _tensorboard(self) -> Any:
        """A SummaryWriter for the run, purging events past the resumed step (a killed run's tail)."""
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as err:
            raise ValueError("TensorBoard logging needs: pip install 'reach[tensorboard]'") from err
        return SummaryWriter(str(self.run_dir / "tensorboard"), purge_step=self.step + 1 if self.step else None)

    # ------------------------------------------------------------------ loop
    def stop_reason(self) -> str | None:
        """Why the run would stop now (a stop rule that holds), or None while it has work left."""
        c = self.config
        if c.steps is not None and self.step >= c.steps:
            return f"reached {c.steps} steps"
        if c.budget_s is not None and self.wall >= c.budget_s:
            return f"reached the time budget of {c.budget_s:.0f} s"
        if c.target_loss is not None and self.loss_ema is not None and self.loss_ema <= c.target_loss:
            return f"loss {self.loss_ema:.3g} reached the target {c.target_loss:g}"
        return None

    def train(self) -> dict[str, Any]:
        """Train until a stop rule holds; returns a summary.

        The run directory is locked for the whole call (a second process training into it gets a
        ``ValueError`` naming this one). SIGINT (Ctrl-C) and SIGTERM finish the current step, save a
        checkpoint and raise :class:`TrainingInterrupted`; :meth:`resume` continues from there.
        Raises :class:`TrainingDivergedError` when the loss becomes NaN or inf. Unless the caller
        chose a thread count, torch uses the cores other processes leave free
        (:func:`reach.threads.thread_policy`)."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with run_lock(self.run_dir), _deferred_signals() as stop, thread_policy():
            return self._train(stop)

    def _train(self, stop: dict[str, int]) -> dict[str, Any]:
        c = self.config
        cfg_path = self.run_dir / "config.json"
        with atomic_path(cfg_path) as tmp:
            Path(tmp).write_text(c.to_json())
        board = self._tensorboard() if c.tensorboard else None
        metrics = open(self.run_dir / "metrics.jsonl", "a")  # noqa: SIM115 - kept open for the loop
        last_ckpt = last_eval = time.perf_counter()
        window_start, window_steps = time.perf_counter(), 0
        total = c.steps if c.steps is not None else None
        # without an explicit `disable`, tqdm honours TQDM_DISABLE=1 (CI) and hides itself off a terminal
        bar = tqdm(
            total=total,
            initial=self.step,
            desc=f"{c.system} {c.layout}",
            unit="step",
            **({} if self.progress else {"disable": True}),
        )
        reason = self.stop_reason()
        # snapshots past the checkpoint (a killed run) are retaken as the resumed run passes them
        snapshots_taken = self._snapshots_due()
        try:
            while reason is None:
                t0 = time.perf_counter()
                frac = self.progress_fraction()
                lr = self.learning_rate(frac)
                for group in self.optimizer.param_groups:
                    group["lr"] = lr
                tmax = self.time_range(frac)
                self._refresh_labels(tmax)  # counted as training time: it is part of the recipe's cost
                x, t, mask = self._sample(tmax)
                pde = not (c.parameterisation == "vanilla" and frac < c.pretrain)
                loss, terms = training_loss(
                    self.network,
                    x,
                    t,
                    norm=c.loss,
                    boundary_mask=mask,
                    boundary_weight=c.boundary_weight,
                    pde=pde,
                    residual_fn=self.residual_fn,
                    gradient_bound=self.gradient_bound,
                    gradient_weight=c.gradient_weight,
                    upper_bound=None if self.upper_bound is None else self._upper_bound_at(x, t),
                    upper_bound_weight=c.upper_bound_weight,
                    lower_bound=self.labels,
                    lower_bound_weight=c.lower_bound_weight,
                )
                if not math.isfinite(terms["loss"]):
                    raise TrainingDivergedError(
                        f"loss became {terms['loss']} at step {self.step + 1}; the last good checkpoint "
                        f"(step {self._checkpoint_step()}) is kept in {self.checkpoint_path}"
                    )
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                self.optimizer.step()
                self.step += 1
                self.wall += time.perf_counter() - t0
                window_steps += 1
                self.loss_ema = terms["loss"] if self.loss_ema is None else 0.95 * self.loss_ema + 0.05 * terms["loss"]
                bar.update(1)
                now = time.perf_counter()
                if self.step % c.log_every == 0 or self.stop_reason():
                    rate = window_steps / max(now - window_start, 1e-9)
                    window_start, window_steps = now, 0
                    row = {
                        "step": self.step,
                        "wall": round(self.wall, 3),
                        "lr": lr,
                        "tmax": tmax,
                        "steps_per_s": round(rate, 3),
                        "points_per_s": round(rate * c.points, 1),
                        **terms,
                    }
                    if self.evaluator is not None and (now - last_eval >= c.eval_every_s or self.stop_reason()):
                        row.update(self.evaluator(NeuralValueFunction(self.network)))
                        last_eval = window_start = time.perf_counter()  # evaluation is not training time
                    metrics.write(json.dumps(row) + "\n")
                    metrics.flush()
                    if board is not None:
                        for key, value in row.items():
                            if key != "step" and isinstance(value, (int, float)):
                                board.add_scalar(key, value, self.step)
                    left = (c.budget_s - self.wall) if c.budget_s else None
                    bar.set_postfix(
                        loss=f"{terms['loss']:.3g}",
                        steps_s=f"{rate:.1f}",
                        left=f"{left:.0f}s" if left is not None else "-",
                    )
                due = self._snapshots_due()
                if due > snapshots_taken:
                    self._snapshot(due)
                    snapshots_taken = due
                if time.perf_counter() - last_ckpt >= c.checkpoint_every_s:
                    self._save()
                    last_ckpt = time.perf_counter()
                if stop:
                    self._save()
                    name = signal.Signals(stop["signal"]).name
                    raise TrainingInterrupted(
                        f"{name} at step {self.step}: saved {self.checkpoint_path}; continue with "
                        f"`reach train --resume {self.run_dir}`"
                    )
                reason = self.stop_reason()
            if c.snapshots and not (self.snapshot_dir / f"{c.snapshots:03d}.pt").exists():
                self._snapshot(c.snapshots)  # a run stopped early (target loss): its end is the last snapshot
            self._save()
        finally:
            bar.close()
            metrics.close()
            if board is not None:
                board.close()
        return {
            "run_dir": str(self.run_dir),
            "steps": self.step,
            "wall_time_s": self.wall,
            "loss_ema": self.loss_ema,
            "stopped": reason,
        }

    def _checkpoint_step(self) -> int | None:
        if not self.checkpoint_path.exists():
            return None
        return json.loads(self.checkpoint_path.with_suffix(".json").read_text()).get("steps")
