"""Training configuration: every knob of a run, stored resolved in the run directory as JSON."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass, field
from typing import Any

from reach.systems import ControlAffineSystem
from reach.systems.registry import SystemSpecified
from reach.validation import check_device, check_float, check_int, check_known_fields, check_seed
from training.layers import parse_layout
from training.network import LEARNED_BOUNDARY, check_parameterisation


def parse_duration(text: str | float | int) -> float:
    """Seconds from ``"90"``, ``"90s"``, ``"10m"``, ``"1.5h"`` (numbers are seconds)."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        seconds = float(text)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([smh]?)\s*", str(text))
        if not m:
            raise ValueError(f"duration must look like 90, 90s, 10m or 1.5h, got {text!r}")
        seconds = float(m.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[m.group(2)]
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"duration must be positive, got {text!r}")
    return seconds


#: runs this long compile their step by default (:meth:`TrainConfig.compile_resolved`)
COMPILE_MIN_STEPS = 2000
COMPILE_MIN_BUDGET_S = 120.0


#: kinds of lower-bound labels (``TrainConfig.lower_bound``; training.policy_lower_bounds)
LOWER_BOUNDS = ("policy", "mpc")


@dataclass
class TrainConfig(SystemSpecified):
    """A training run. At least one stop rule (``steps``, ``budget_s`` or ``target_loss``) is needed.

    ``system`` is a registered name, an import path (``pkg.module:ClassName``) or a system instance;
    an instance is stored as its reference and parameters (:class:`~reach.systems.registry.SystemSpecified`).
    """

    system: str | ControlAffineSystem = "air3d"
    system_parameters: dict[str, Any] = field(default_factory=dict)
    layout: str = "ssssl"
    width: int = 128
    w0: float = 30.0
    parameterisation: str = "exact"
    sincos: bool = True  # encode periodic dimensions as (sin, cos): no seam at +-pi
    sincos_radius: float = 1 / math.pi  # ... scaled by this: a turn spans as much input as the plain encoding
    value_scale: float | None = None  # None: the system's own (ControlAffineSystem.value_scale, 1 unless declared)
    points: int = 8192
    lr: float = 1e-4
    lr_final: float = 1e-5  # cosine decay from lr to lr_final over the run
    schedule: str = "cosine"  # or "constant"
    loss: str = "l1"  # "l1" or "l2" on the HJI residual
    gradient_bound: float | None = 3.0  # penalise |dV/dx| above this many times l's steepest slope: no cliffs
    gradient_weight: float = 1.0
    # multi-vehicle systems: a pair grid solution (.npz) whose union of pairwise values bounds V from
    # above; the loss adds upper_bound_weight * mean(relu(V - V_union)) where a pair's grid covers the state
    upper_bound: str | None = None
    upper_bound_weight: float = 1.0
    # systems without a disturbance: "policy" labels lower_bound_points sampled states every
    # lower_bound_every steps with what the network's own policy achieves (training.policy_lower_bounds, a lower
    # bound of V), "mpc" with the best of sampled control sequences bootstrapped by the network;
    # the loss adds lower_bound_weight * mean(relu(J - V)) on them
    lower_bound: str | None = None
    lower_bound_weight: float = 1.0
    lower_bound_points: int = 1024
    lower_bound_every: int = 100
    lower_bound_dt: float = 0.01  # step of the labelling rollouts (RK4, inputs held)
    # "mpc" only: control sequences per state, their horizon (s) and perturbation (x half-width)
    lower_bound_samples: int = 16
    lower_bound_horizon: float = 0.1
    lower_bound_noise: float = 0.5
    # share of each step's points drawn near the network's own zero level: level_candidates times as
    # many uniform (x, t) are drawn and the ones with the smallest |V| kept (the BRT's boundary, where
    # a sign error makes a state false safe and the PDE residual alone samples thinly)
    zero_level_fraction: float = 0.0
    zero_level_candidates: int = 4
    gradients: str = "fused"  # input derivatives: "fused" (hand-carried, one backward) or "autograd" (double backward)
    compile: bool | None = None  # torch.compile the fused residual; None: when the run is long enough (see below)
    # replay each step as one CUDA graph (training.cuda_graph); None: on a CUDA device where the run
    # allows it (cuda_graph_unsupported), True: require it, False: never
    cuda_graph: bool | None = None
    # "tf32": a CUDA GPU's TF32 tensor cores do the float32 matrix products (10-bit mantissas in,
    # float32 sums): faster, not exact (measured: docs/results/benchmarks.md, *The GPU step as one CUDA graph*)
    matmul_precision: str = "float32"
    curriculum: float = 0.5  # share of the run over which the sampled time range grows to the horizon
    pretrain: float = 0.0  # vanilla only: share of the run spent on the boundary loss alone
    boundary_fraction: float = 0.15  # vanilla only: share of points sampled at t = 0
    boundary_weight: float = 1.0  # vanilla only
    steps: int | None = None
    budget_s: float | None = None
    target_loss: float | None = None
    seed: int = 0
    device: str = "cpu"
    log_every: int = 25
    checkpoint_every_s: float = 30.0
    eval_every_s: float = 60.0
    tensorboard: bool = False  # also log the metrics as TensorBoard scalars in RUN/tensorboard (reach[tensorboard])
    snapshots: int = 0  # evenly spaced network snapshots over the run (RUN/snapshots/NNN.pt); needs steps or budget_s

    def __post_init__(self) -> None:
        self.take_system_instance()

    def validate(self) -> TrainConfig:
        parse_layout(self.layout)
        if self.steps is None and self.budget_s is None and self.target_loss is None:
            raise ValueError("give at least one stop rule: steps, budget_s or target_loss")
        checks = {
            "width": self.width >= 1,
            "points": self.points >= 1,
            "lr": self.lr > 0,
            "lr_final": self.lr_final > 0,
            "w0": self.w0 > 0,
            "value_scale": self.value_scale is None or self.value_scale > 0,
            "sincos_radius": self.sincos_radius > 0,
            "gradient_bound": self.gradient_bound is None or self.gradient_bound > 0,
            "gradient_weight": self.gradient_weight >= 0,
            "upper_bound_weight": self.upper_bound_weight >= 0,
            "lower_bound_weight": self.lower_bound_weight >= 0,
            "lower_bound_points": self.lower_bound_points >= 1,
            "lower_bound_every": self.lower_bound_every >= 1,
            "lower_bound_dt": self.lower_bound_dt > 0,
            "lower_bound_samples": self.lower_bound_samples >= 1,
            "lower_bound_horizon": self.lower_bound_horizon > 0,
            "lower_bound_noise": self.lower_bound_noise >= 0,
            "zero_level_fraction": 0 <= self.zero_level_fraction < 1,
            "zero_level_candidates": self.zero_level_candidates >= 2,
            "curriculum": 0 <= self.curriculum <= 1,
            "pretrain": 0 <= self.pretrain < 1,
            "boundary_fraction": 0 < self.boundary_fraction < 1,
            "steps": self.steps is None or self.steps >= 1,
            "budget_s": self.budget_s is None or self.budget_s > 0,
            "log_every": self.log_every >= 1,
            "snapshots": isinstance(self.snapshots, int) and self.snapshots >= 0,
            # a non-positive or NaN target is never reached: as the only stop rule it would train forever
            "target_loss": self.target_loss is None or self.target_loss > 0,
            "checkpoint_every_s": self.checkpoint_every_s >= 0,
            "eval_every_s": self.eval_every_s >= 0,
        }
        for name in (
            "lr",
            "lr_final",
            "w0",
            "value_scale",
            "sincos_radius",
            "gradient_bound",
            "gradient_weight",
            "upper_bound_weight",
            "lower_bound_weight",
            "lower_bound_dt",
            "lower_bound_horizon",
            "lower_bound_noise",
            "zero_level_fraction",
            "curriculum",
            "pretrain",
            "boundary_fraction",
            "budget_s",
            "target_loss",
            "checkpoint_every_s",
            "eval_every_s",
            "boundary_weight",
        ):
            value = getattr(self, name)
            if value is not None:
                check_float(name, value)  # numbers, finite: NaN passes every comparison-free check
        for name in (
            "width",
            "points",
            "log_every",
            "snapshots",
            "steps",
            "lower_bound_points",
            "lower_bound_every",
            "lower_bound_samples",
            "zero_level_candidates",
        ):
            value = getattr(self, name)
            if value is not None:
                check_int(name, value)
        check_seed("seed", self.seed)
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"invalid {name}: {getattr(self, name)!r}")
        check_device(self.device)
        system = self.build_system()  # an unknown system or parameter fails here
        if self.snapshots and self.steps is None and self.budget_s is None:
            raise ValueError("snapshots are spaced over steps or budget_s; give one of them")
        if self.parameterisation in LEARNED_BOUNDARY and self.boundary_fraction + self.zero_level_fraction >= 1:
            raise ValueError(
                f"boundary_fraction + zero_level_fraction must stay below 1 (the rest are the PDE's uniform points), "
                f"got {self.boundary_fraction} + {self.zero_level_fraction}"
            )
        check_parameterisation(self.parameterisation, system)
        if self.schedule not in ("cosine", "constant"):
            raise ValueError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}")
        if self.gradients not in ("fused", "autograd"):
            raise ValueError(f"gradients must be 'fused' or 'autograd', got {self.gradients!r}")
        if self.compile not in (None, True, False):
            raise ValueError(f"compile must be true, false or null (auto), got {self.compile!r}")
        if self.matmul_precision not in ("float32", "tf32"):
            raise ValueError(f"matmul_precision must be 'float32' or 'tf32', got {self.matmul_precision!r}")
        if self.matmul_precision == "tf32" and str(self.device).split(":")[0] != "cuda":
            raise ValueError(f"matmul_precision='tf32' is a CUDA GPU's mode, and the run trains on {self.device!r}")
        if self.cuda_graph not in (None, True, False):
            raise ValueError(f"cuda_graph must be true, false or null (auto), got {self.cuda_graph!r}")
        if self.cuda_graph and (why := self.cuda_graph_unsupported()):
            raise ValueError(f"cuda_graph=True, but this run cannot replay its step as a CUDA graph: {why}")
        if self.compile and self.gradients != "fused":
            raise ValueError("compile needs gradients='fused' (torch.compile does not take double backward)")
        if self.upper_bound is not None and (not isinstance(self.upper_bound, str) or not self.upper_bound):
            raise ValueError(
                "upper_bound must be the path of a pair grid solution or pretrained:relativepair, "
                f"got {self.upper_bound!r}"
            )
        if self.lower_bound is not None and self.lower_bound not in LOWER_BOUNDS:
            raise ValueError(f"lower_bound must be one of {LOWER_BOUNDS} or null (none), got {self.lower_bound!r}")
        if self.loss not in ("l1", "l2"):
            raise ValueError(f"loss must be 'l1' or 'l2', got {self.loss!r}")
        return self

    def cuda_graph_unsupported(self) -> str | None:
        """Why this run's step cannot be replayed as a CUDA graph (:mod:`training.cuda_graph`), or
        ``None`` when it can. A graph replays fixed kernels on fixed memory, so nothing in the step may
        read a value back from the device or pick a data-dependent number of points."""
        if str(self.device).split(":")[0] != "cuda":
            return f"CUDA graphs need a CUDA device, and the run trains on {self.device!r}"
        if self.parameterisation in LEARNED_BOUNDARY:
            return (
                f"the {self.parameterisation} parameterisation's boundary term selects its points by a mask "
                "(a data-dependent count), and it pretrains on another loss"
            )
        if self.gradients != "fused":
            return "gradients='autograd': the graphed step is built and measured for fused gradients only"
        return None

    def compile_resolved(self) -> bool | None:
        """Whether to compile: ``compile`` if given, else (``None``, auto) for fused runs of at least
        :data:`COMPILE_MIN_STEPS` steps or :data:`COMPILE_MIN_BUDGET_S` seconds, where the one-off
        compilation pays for itself (measured: docs/results/training.md, *Training throughput*);
        shorter runs (tests, smoke runs) stay eager. Auto falls back to eager mode with a warning when
        compiling fails (returns ``None``)."""
        if self.compile is not None or self.gradients != "fused":
            return self.compile if self.gradients == "fused" else False
        long_run = (self.steps or 0) >= COMPILE_MIN_STEPS or (self.budget_s or 0) >= COMPILE_MIN_BUDGET_S
        return None if long_run else False

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        check_known_fields(cls, d, "training config")
        return cls(**d).validate()
