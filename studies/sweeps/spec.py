"""What a layout sweep is: the systems, layouts, seeds, budget and evaluation it was run with.

A :class:`SweepSpec` is stored as ``OUT/sweep.json``. Rerunning a sweep into the same directory
must use the same spec, except that layouts and seeds may be added or dropped (the study grows or
is reported on a subset); any other difference (budget, width, evaluation, ...) is refused with
the keys that differ, because the stored runs would no longer be comparable with new ones.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from reach.atomic import atomic_path
from reach.json_files import read_json
from reach.systems import MultiVehicle, make_system
from reach.systems.registry import SystemSpecified
from reach.validation import check_known_fields
from training.config import TrainConfig
from training.layers import parse_layout

FORMAT = "reach.sweep.v1"

#: the seed paper's Air3D layouts (all four-layer)
AIR3D_LAYOUTS = ("ssssl", "ssrsl", "srsrl", "rrrsl", "srrrl", "rrrrl")
#: the seed paper's 9D layouts studied here: the Air3D six plus three of its six-layer ones
NINE_D_LAYOUTS = (*AIR3D_LAYOUTS, "sssssl", "ssrrsl", "srsrrl")


def default_layouts(system: Any) -> list[str]:
    """Layouts a sweep compares when none are given: the 9D study's for the multi-vehicle systems, the
    paper's six (:data:`AIR3D_LAYOUTS`) for Air3D and for any other system, a user's own included."""
    return list(NINE_D_LAYOUTS if isinstance(make_system(system), MultiVehicle) else AIR3D_LAYOUTS)


#: keys that may differ between runs into one sweep directory
GROWABLE = ("layouts", "seeds")

#: training fields a sweep fixes itself (the rest may be set through ``SweepSpec.train``)
_SWEEP_OWNED = {"system", "system_parameters", "layout", "seed", "budget_s", "steps", "snapshots", "width", "device"}


@dataclass
class SweepSpec(SystemSpecified):
    """Every (layout, seed) is trained with the same budget and evaluated at ``snapshots`` points.

    ``evaluation`` is ``"groundtruth"`` (value MSE and BRT IoU against a grid solution, for systems
    of at most 3 dimensions) or ``"rollout"`` (violation rate, delta-level and scenario volume from
    ``samples`` rollouts); ``"auto"`` picks the first where a grid is feasible. Rollouts are costly,
    so with ``rollout_every = k`` only every k-th snapshot (and always the last) is rolled out.
    ``pairwise`` (a two-car ``relativepair`` solution) adds the share of states in the union of
    pairwise BRTs that a network calls safe, which a sound model keeps at zero.
    """

    system: Any = "air3d"  # a registered name, an import path or a system instance
    system_parameters: dict[str, Any] = field(default_factory=dict)
    layouts: list[str] = field(default_factory=lambda: list(AIR3D_LAYOUTS))
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    budget_s: float | None = 300.0
    steps: int | None = None
    snapshots: int = 10
    width: int = 128
    device: str = "cpu"
    train: dict[str, Any] = field(default_factory=dict)
    evaluation: str = "auto"
    grid: int = 101
    groundtruth: str | None = None
    eval_time: float | None = None
    slice_value: float | None = None  # None: the system's reference slice value
    samples: int = 10_000
    scenario_samples: int | None = None
    rollout_every: int = 1
    eval_seed: int = 0
    pairwise: str | None = None

    def __post_init__(self) -> None:
        self.take_system_instance()
        self.layouts = [str(x) for x in self.layouts]
        self.seeds = [int(s) for s in self.seeds]

    # ------------------------------------------------------------------ validation
    def validate(self) -> SweepSpec:
        """Raise ``ValueError`` naming the bad value; returns ``self`` with ``evaluation`` resolved."""
        if not self.layouts:
            raise ValueError("a sweep needs at least one layout")
        for layout in self.layouts:
            parse_layout(layout)
        if len(set(self.layouts)) != len(self.layouts):
            raise ValueError(f"layouts repeat: {self.layouts}")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds must be distinct and at least one, got {self.seeds}")
        if self.budget_s is None and self.steps is None:
            raise ValueError("a sweep needs a budget (seconds) or a step count per run")
        if self.snapshots < 1:
            raise ValueError(f"snapshots must be >= 1, got {self.snapshots}")
        if self.rollout_every < 1:
            raise ValueError(f"rollout_every must be >= 1, got {self.rollout_every}")
        if self.samples < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        owned = _SWEEP_OWNED & set(self.train)
        if owned:
            raise ValueError(f"training options {sorted(owned)} are set by the sweep itself, not through `train`")
        known = {f.name for f in dataclasses.fields(TrainConfig)}
        unknown = sorted(set(self.train) - known)
        if unknown:
            raise ValueError(f"unknown training options {unknown} (known: {sorted(known - _SWEEP_OWNED)})")
        if self.groundtruth is not None:
            from groundtruth.solution import GridSolution  # lazy: the grid solution only when a ground truth is given

            reference = GridSolution.load(self.groundtruth)
            wanted = self.build_system()
            wanted.require_same_physics(reference.system, f"ground truth {self.groundtruth}")
        system = self.build_system()
        if self.evaluation == "auto":
            self.evaluation = "groundtruth" if system.state_dim <= 3 else "rollout"
        if self.evaluation not in ("groundtruth", "rollout"):
            raise ValueError(f"evaluation must be 'auto', 'groundtruth' or 'rollout', got {self.evaluation!r}")
        if self.pairwise is not None and self.evaluation != "rollout":
            raise ValueError("pairwise containment is a rollout-evaluation metric (multi-vehicle systems)")
        if self.pairwise is not None and not Path(self.pairwise).exists():
            raise ValueError(f"pairwise solution {self.pairwise} does not exist")
        if self.slice_value is None:  # stored resolved, so a sweep's spec does not change with the default
            self.slice_value = system.reference_slice()[1]
        if self.evaluation == "groundtruth" and system.state_dim > 3:
            raise ValueError(f"{self.system} has {system.state_dim} dimensions; a grid ground truth needs at most 3")
        for layout in self.layouts[:1]:
            self.train_config(layout, self.seeds[0])  # TrainConfig checks the training options
        return self

    def train_config(self, layout: str, seed: int) -> TrainConfig:
        """The training run of one (layout, seed)."""
        return TrainConfig(
            system=self.system,
            system_parameters=dict(self.system_parameters),
            layout=layout,
            width=self.width,
            budget_s=self.budget_s,
            steps=self.steps,
            seed=seed,
            snapshots=self.snapshots,
            device=self.device,
            **self.train,
        ).validate()

    def tasks(self) -> list[tuple[str, int]]:
        """Every (layout, seed), layouts outermost."""
        return [(layout, seed) for layout in self.layouts for seed in self.seeds]

    def rolled_out(self, snapshot: int) -> bool:
        """Whether snapshot ``snapshot`` (1-based) is evaluated (always, except for sparse rollouts)."""
        return self.evaluation != "rollout" or snapshot % self.rollout_every == 0 or snapshot == self.snapshots

    # ------------------------------------------------------------------ storage
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SweepSpec:
        check_known_fields(cls, data, "sweep spec")
        return cls(**data)

    def differences(self, other: SweepSpec) -> list[str]:
        """Keys (other than the growable ones) whose values differ, formatted ``key: a != b``."""
        a, b = self.to_dict(), other.to_dict()
        return [f"{k}: {a[k]!r} != {b[k]!r}" for k in a if k not in GROWABLE and a[k] != b[k]]


def store_spec(spec: SweepSpec, out: str | os.PathLike) -> None:
    """Write ``OUT/sweep.json``, refusing a spec that is incomparable with the one stored there."""
    path = Path(out) / "sweep.json"
    if path.exists():
        diff = spec.differences(load_spec(out))
        if diff:
            raise ValueError(
                f"{path} holds a sweep with other settings ({'; '.join(diff)}); only layouts and seeds may "
                "change between runs into one directory: use another --out"
            )
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps({"format": FORMAT, "spec": spec.to_dict()}, indent=2, sort_keys=True))


def load_spec(out: str | os.PathLike) -> SweepSpec:
    """The spec stored in a sweep directory."""
    path = Path(out) / "sweep.json"
    data = read_json(path, "a reach sweep", expect_format=FORMAT, hint="; move it away to start the sweep over")
    return SweepSpec.from_dict(data["spec"])
