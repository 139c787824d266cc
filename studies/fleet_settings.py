"""The fleet study's settings (:mod:`studies.fleet_eval`), in a module of their own so that the
command line reads their defaults without loading the envs (``reach_cli`` builds its parser light)."""

from __future__ import annotations

from dataclasses import dataclass

from reach.validation import check_float, check_int, check_seed, positive_finite

__all__ = ["METHODS", "FleetEvalSettings"]

#: the study's methods: unfiltered, the fleet filter, the distance CBF-QP, the naive union switch
METHODS = ("none", "fleet", "cbf", "union")


@dataclass(frozen=True)
class FleetEvalSettings:
    """What :func:`run_fleet_eval` runs; refused at construction, naming the bad value."""

    #: the fleet scenes' layouts (None: every layout, :data:`reach_envs.fleet_scenes.LAYOUTS`)
    layouts: tuple[str, ...] | None = None
    #: the fleet sizes (cars)
    sizes: tuple[int, ...] = (4, 8, 16, 32, 64)
    #: the methods compared
    methods: tuple[str, ...] = METHODS
    #: episodes per layout, size and method
    episodes: int = 1000
    #: episodes simulated at once (the episodes of a cell run in batches of this many)
    batch: int = 250
    #: the episodes' seed (the same initial states for every method of a layout and size)
    seed: int = 0
    #: the scenario bound's confidence is ``1 - beta``
    beta: float = 1e-6
    #: decisions timed per layout, size and method at batch 1 on one thread (0: not timed)
    timing_ticks: int = 100
    #: cars per unit area of the ``random-goals`` arena (:class:`~reach_envs.fleet_scenes.FleetScene`)
    density: float = 0.1
    #: seconds the fleet filter's greedy policy holds each candidate (``FleetFilterSettings.hold``;
    #: None: the filter's default, :data:`safety.fleet.greedy.HOLD`, which the results record)
    hold: float | None = None
    #: seconds of closing speed the fleet filter's default pair threshold keeps in hand
    #: (``FleetFilterSettings.reaction_time``; None: the filter's default,
    #: :data:`safety.fleet.filter.REACTION_TIME`, which the results record)
    reaction_time: float | None = None
    #: how the fleet filter's greedy policy breaks ties (``FleetFilterSettings.tie_break``; None: the
    #: filter's default, which the results record)
    tie_break: str | None = None
    #: collided episodes kept per layout, size and method to replay alone (the first ones; 0: none).
    #: A 64-car episode's file is about 2 MB, and an unfiltered fleet collides in nearly every one
    keep_collisions: int = 10

    def __post_init__(self) -> None:
        from reach_envs.fleet_scenes import LAYOUTS, FleetScene  # lazy: the envs stack only once settings are made
        from safety.fleet.greedy import TIE_BREAKS  # lazy: as above

        if self.layouts is None:
            object.__setattr__(self, "layouts", LAYOUTS)
        for name, known in (("layouts", LAYOUTS), ("methods", METHODS)):
            values = tuple(getattr(self, name))
            if not values or any(v not in known for v in values):
                raise ValueError(f"FleetEvalSettings: {name} must be among {known}, got {values!r}")
            object.__setattr__(self, name, values)
        sizes = tuple(self.sizes)
        if not sizes or any(isinstance(n, bool) or not isinstance(n, int) or n < 2 for n in sizes):
            raise ValueError(f"FleetEvalSettings: sizes must be integers >= 2, got {self.sizes!r}")
        object.__setattr__(self, "sizes", sizes)
        check_int("FleetEvalSettings: episodes", self.episodes, low=1)
        check_int("FleetEvalSettings: batch", self.batch, low=1)
        check_int("FleetEvalSettings: timing_ticks", self.timing_ticks, low=0)
        check_int("FleetEvalSettings: keep_collisions", self.keep_collisions, low=0)
        check_seed("FleetEvalSettings: seed", self.seed)
        check_float("FleetEvalSettings: beta", self.beta, low=0.0, high=1.0, low_open=True, high_open=True)
        FleetScene(layout="random-goals", n_cars=2, density=self.density)  # refused there, naming it
        if self.hold is not None:
            object.__setattr__(self, "hold", positive_finite("FleetEvalSettings: hold", self.hold))
        if self.tie_break is not None and self.tie_break not in TIE_BREAKS:
            raise ValueError(f"FleetEvalSettings: tie_break must be one of {TIE_BREAKS}, got {self.tie_break!r}")
        if self.reaction_time is not None:
            rt = check_float("FleetEvalSettings: reaction_time", self.reaction_time, low=0.0)
            object.__setattr__(self, "reaction_time", rt)
