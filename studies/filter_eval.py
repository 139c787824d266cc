"""What a safety filter buys and what it costs, measured over episodes: the names, re-exported.

This module was split by job; it re-exports every name it had, so ``from studies.filter_eval
import ...`` (and the deprecated ``safety.filter_eval``, :mod:`reach.deprecation`) keeps working.
New code imports from the module that holds a name:

* :mod:`studies.filter_configs` - :class:`FilterConfig`, the filter grid, episode and output settings;
* :mod:`studies.filter_episodes` - :func:`evaluate_filters`, :func:`evaluate_filter_parallel`,
  :func:`outside_states` (running episodes with and without filters, the tally);
* :mod:`studies.filter_tables` - rows as tables and results files, merging into a table;
* :mod:`studies.filter_study` - :func:`run_filter_study` (the pipeline) and :func:`record_side_by_side`;
* :mod:`safety.filter_settings` - :class:`~safety.filter_settings.FilterSettings`, the filter's own options.
"""

from __future__ import annotations

# names this module imported before the split, importable from here as they were
from reach.locking import exclusive_lock as exclusive_lock
from reach.value_function import ValueFunction as ValueFunction
from reach_envs.scenes import Scene as Scene
from reach_envs.scenes import make_scene as make_scene
from reach_envs.vector import ReachVectorEnv as ReachVectorEnv
from safety.filter import check_filter_settings as check_filter_settings
from safety.filter_settings import DEFAULT_GAMMA as DEFAULT_GAMMA
from safety.filter_settings import FilterSettings as FilterSettings
from safety.filter_settings import default_threshold
from safety.filter_settings import resolve_policy as resolve_policy
from safety.metrics import wilson_interval as wilson_interval
from safety.value_policies import worst_case_disturbance as worst_case_disturbance
from safety.wrappers import SafetyFilterParallelWrapper as SafetyFilterParallelWrapper
from safety.wrappers import SafetyFilterVectorWrapper as SafetyFilterVectorWrapper
from studies.filter_configs import START_FROM as START_FROM
from studies.filter_configs import EpisodeSettings as EpisodeSettings
from studies.filter_configs import FilterConfig
from studies.filter_configs import FilterGrid as FilterGrid
from studies.filter_configs import FilterStudySettings as FilterStudySettings
from studies.filter_configs import StudyOutput as StudyOutput
from studies.filter_episodes import _scene as _scene
from studies.filter_episodes import _Tally as _Tally
from studies.filter_episodes import evaluate_filter_parallel, evaluate_filters, outside_states
from studies.filter_study import FilterStudy, record_side_by_side, run_filter_study
from studies.filter_tables import FILTER_COLUMNS as FILTER_COLUMNS
from studies.filter_tables import (
    PER_INVOCATION_KEYS,
    backup_horizon_of,
    filter_table_rows,
    labelled,
    merge_filter_results,
)
from studies.filter_tables import _episode_header as _episode_header
from studies.filter_tables import _stored_filter_table as _stored_filter_table
from studies.filter_tables import _with_interval as _with_interval
from studies.filter_tables import filter_table as filter_table
from studies.filter_tables import write_filter_results as write_filter_results
from studies.tables import merge_rows as merge_rows
from studies.tables import write_results as write_results
from studies.tasks import GoalTask as GoalTask
from studies.tasks import NominalPolicy as NominalPolicy
from studies.tasks import make_task as make_task

_backup_horizon = backup_horizon_of  # the private names of before the split
_labelled = labelled

__all__ = [
    "PER_INVOCATION_KEYS",
    "FilterConfig",
    "FilterStudy",
    "default_threshold",
    "evaluate_filter_parallel",
    "evaluate_filters",
    "filter_table_rows",
    "merge_filter_results",
    "outside_states",
    "record_side_by_side",
    "run_filter_study",
]
