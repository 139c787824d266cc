"""What a filter study sets up, as frozen settings: its configurations, episodes and outputs.

Why a module of its own: these objects are light (no Gymnasium, no Matplotlib), so ``reach
filter-eval`` reads its option defaults from them at start-up, and the modules that run episodes
(:mod:`studies.filter_episodes`), write tables (:mod:`studies.filter_tables`) and orchestrate a study
(:mod:`studies.filter_study`) share them without importing each other.

* :class:`FilterConfig` - one row of a study: a label, a value function (``None``: the nominal
  policy alone) and its :class:`~safety.filters.settings.FilterSettings`;
* :class:`FilterGrid` - the filters a study compares (kinds x thresholds x gammas, the rest shared);
* :class:`EpisodeSettings` - the episodes every configuration runs;
* :class:`StudyOutput` - what the study writes besides its table;
* :class:`FilterStudySettings` - the three groups, and the flat keywords of ``run_filter_study``.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from safety.filters.settings import FIELDS, FilterSettings, make_filter_settings

if TYPE_CHECKING:
    from reach.value_function import ValueFunction
    from studies.goal_tasks import NominalPolicy

#: where :func:`~studies.filter_episodes.outside_states` draws candidate starts: the system's whole
#: domain, or the scene's own starts
START_FROM = ("domain", "scene")

#: the :class:`FilterSettings` fields a :class:`FilterGrid` sets per configuration
GRID_VARIED = ("kind", "threshold", "gamma")


@dataclass(frozen=True, init=False)
class FilterConfig:
    """One configuration: a label, a value function (``None``: the nominal policy alone) and the
    filter's :class:`~safety.filters.settings.FilterSettings`.

    ``FilterConfig(label, value_function=None, threshold=None, *, settings=None, **options)``: the
    threshold and any settings field by keyword (``kind="lookahead", backup_horizon=0.5``) make or
    replace the settings (:func:`~safety.filters.settings.make_filter_settings`), checked here,
    before any episode runs. The settings' fields read back as attributes (``config.kind``).
    """

    label: str
    value_function: ValueFunction | None
    settings: FilterSettings

    def __init__(
        self,
        label: str,
        value_function: ValueFunction | None = None,
        threshold: float | None = None,
        *,
        settings: FilterSettings | None = None,
        **options: Any,
    ) -> None:
        object.__setattr__(self, "label", label)
        object.__setattr__(self, "value_function", value_function)
        object.__setattr__(self, "settings", make_filter_settings(settings, threshold=threshold, **options))

    def __getattr__(self, name: str) -> Any:
        if name in FIELDS:  # never "settings" itself: no recursion before __init__ sets it
            return getattr(self.settings, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def filtered(self) -> bool:
        """Whether this configuration filters (it has a value function)."""
        return self.value_function is not None

    def filter_options(self) -> dict[str, Any]:
        """The filter's settings as the keyword arguments every filter wrapper takes (threshold and
        time-to-go aside, which the wrappers take by position)."""
        return {k: v for k, v in self.settings.keywords().items() if k not in ("threshold", "time_to_go")}


@dataclass(frozen=True)
class FilterGrid:
    """The filters a study compares: each value function under every kind in ``kinds`` at every
    threshold (and, for ``"smooth"``, every ``gamma``), sharing the rest of ``shared`` (time-to-go,
    backup horizon and disturbance, backup policy). Every combination is checked when the grid is made."""

    thresholds: Sequence[float | None] = (FilterSettings.threshold,)
    kinds: Sequence[str] = (FilterSettings.kind,)
    gammas: Sequence[float] = (FilterSettings.gamma,)
    shared: FilterSettings = field(default_factory=FilterSettings)

    def __post_init__(self) -> None:
        for name in ("thresholds", "kinds", "gammas"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        self._each()  # each combination made once: a bad value is refused now, before any episode runs

    def _each(self) -> list[FilterSettings]:
        return [
            dataclasses.replace(self.shared, kind=kind, threshold=threshold, gamma=gamma)
            for kind in self.kinds
            for threshold in self.thresholds
            for gamma in (self.gammas if kind == "smooth" else (self.shared.gamma,))
        ]

    def configs(self, value_functions: Sequence[tuple[str, ValueFunction]]) -> list[FilterConfig]:
        """The nominal configuration, then every filter of the grid for each ``(label, value function)``."""
        each = self._each()
        return [FilterConfig("nominal")] + [
            FilterConfig(label, vf, settings=settings) for label, vf in value_functions for settings in each
        ]


@dataclass(frozen=True)
class EpisodeSettings:
    """The episodes every configuration of a study runs.

    Attributes:
        episodes: how many; seed: sub-environment ``i`` is seeded ``seed + i``.
        pursuer: ``None`` keeps the scene's disturbance; a name (``"pursue"``, ``"random"``) replaces
            it; a value function makes the pursuer play its worst-case ``d*``.
        start_outside: draw the starts from ``{V > start_margin}`` of this value function: uniform
            over the system's domain (``start_from="domain"``) or among the scene's own starts
            (``"scene"``).
        nominal: the nominal policy (float64 states ``(N, n)`` -> normalised actions ``(N, m_u)``);
            default: the scene system's goal task (:func:`~studies.goal_tasks.make_task`).
        pettingzoo: run through the PettingZoo parallel env, episode by episode, instead.
    """

    episodes: int = 1000
    seed: int = 0
    pursuer: str | ValueFunction | None = None
    start_outside: ValueFunction | None = None
    start_margin: float = 0.1
    start_from: str = "domain"
    nominal: NominalPolicy | None = None
    pettingzoo: bool = False

    def __post_init__(self) -> None:
        if self.start_from not in START_FROM:
            raise ValueError(f"start_from must be one of {START_FROM}, got {self.start_from!r}")


@dataclass(frozen=True)
class StudyOutput:
    """What a study writes besides its table: a side-by-side GIF (``gif``; ``gif_threshold``, default
    the first threshold, is its filters' threshold), extra ``header`` keys of the table, the trade-off
    plot's ``title`` (default: the scene's name), and whether rows ``merge`` into a table of the same
    episodes already at the output path instead of replacing it."""

    gif: str | os.PathLike | None = None
    gif_threshold: float | None = None
    header: Mapping[str, Any] | None = None
    title: str | None = None
    merge: bool = False


@dataclass(frozen=True)
class FilterStudySettings:
    """A filter study's whole set-up, one group per job: its episodes, its filters, its outputs."""

    episodes: EpisodeSettings = field(default_factory=EpisodeSettings)
    filters: FilterGrid = field(default_factory=FilterGrid)
    output: StudyOutput = field(default_factory=StudyOutput)

    @classmethod
    def from_options(cls, settings: FilterStudySettings | None = None, /, **options: Any) -> FilterStudySettings:
        """``settings`` (default: all defaults) with flat keywords replacing fields: each keyword goes
        to the group with a field of its name (``episodes=``, ``kinds=``, ``gif=``, ...), and a
        :class:`FilterSettings` field (``time_to_go=``, ``backup_horizon=``, ``policy=``, ...) to the
        grid's shared settings. Unknown keywords raise ``TypeError`` naming them."""
        study = settings if settings is not None else cls()
        groups = {}
        for f in dataclasses.fields(study):
            group = getattr(study, f.name)
            mine = {k: options.pop(k) for k in [k for k in options if k in group.__dataclass_fields__]}
            groups[f.name] = dataclasses.replace(group, **mine) if mine else group
        varied = sorted(set(options) & set(GRID_VARIED))
        if varied:
            raise TypeError(
                f"{', '.join(varied)}: a study varies these per configuration; give kinds, thresholds, gammas"
            )
        if options:
            grid = groups["filters"]
            groups["filters"] = dataclasses.replace(grid, shared=make_filter_settings(grid.shared, **options))
        return cls(**groups)


__all__ = [
    "GRID_VARIED",
    "START_FROM",
    "EpisodeSettings",
    "FilterConfig",
    "FilterGrid",
    "FilterStudySettings",
    "StudyOutput",
]
