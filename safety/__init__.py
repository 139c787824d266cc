"""Safety core: optimal policies from grad V, a least-restrictive filter, rollouts and verification.

This is the layer above training; batch evaluation tables, filter studies, plots and the demo sit
one floor up, in :mod:`studies`.

Everything here takes a :class:`~reach.value_function.ValueFunction` (a trained
network, a DeepReach import or a grid solution; :func:`load_value_function` loads any of them):

* :class:`OptimalPolicy` - ``u*``, ``d*`` from the gradient through the system's derived functions;
* :class:`GreedyPolicy` - the candidate input held for a short step that leaves the most value (the
  switch filter's default backup input; ``rollout(..., policy="greedy")``);
* :class:`SafetyFilter` and its environment adapters (:mod:`safety.wrappers`), which take one
  :class:`FilterSettings` (kind, threshold, time-to-go, gamma, backup horizon and disturbance, policy);
* :func:`rollout` - batched closed-loop simulation that skips decided trajectories;
* :func:`verify` - violation statistics, delta-level and the scenario guarantee of one value
  function (:func:`studies.evaluate_many` runs it across many checkpoints on the same states);
* :class:`RolloutStore` - rollout outcomes kept block by block, so a long verification resumes;
* :func:`export_filter` - a filter as one ONNX file for the torch-free :mod:`reach_runtime`.
"""

from __future__ import annotations

import importlib
import warnings
from typing import TYPE_CHECKING, Any

from reach.lazy import lazy_exports
from reach.value_function import MinimumOf, value_and_gradient
from safety.filter import FilterInfo, SafetyFilter
from safety.filter_settings import FilterSettings
from safety.metrics import scenario_epsilon, violation_statistics, wilson_interval
from safety.rollout import RolloutResult, RolloutSettings, rollout
from safety.rollout_store import RolloutStore
from safety.sources import LoadedValueFunction, as_value_function, load_value_function
from safety.value_policies import GreedyPolicy, OptimalPolicy, worst_case_disturbance
from safety.verify import VerifySettings, sample_states, sample_superlevel_set, verify

if TYPE_CHECKING:
    from safety.export import export_filter
    from safety.wrappers import SafetyFilterParallelWrapper, SafetyFilterVectorWrapper, SafetyFilterWrapper

#: names whose module loads Gymnasium and PettingZoo (the wrappers) or the ONNX export, imported on first
#: use so that ``import safety.filter`` (the CLI's start-up) stays light. (A name that equals its module's,
#: like ``rollout`` and ``verify``, must stay eager: importing the submodule would shadow it.)
_LAZY = {
    "SafetyFilterParallelWrapper": "safety.wrappers",
    "SafetyFilterVectorWrapper": "safety.wrappers",
    "SafetyFilterWrapper": "safety.wrappers",
    "export_filter": "safety.export",
}


#: names that moved up to :mod:`studies` (deprecated here; removed in reach 0.3)
_MOVED_UP = {"evaluate_many", "load_results", "markdown_table"}


_lazy_getattr, __dir__ = lazy_exports(__name__, _LAZY)


def __getattr__(name: str) -> Any:
    if name in _MOVED_UP:
        warnings.warn(
            f"safety.{name} moved to studies.{name}; import it from there (removed here in reach 0.3)",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module("studies"), name)  # deprecated alias (the one upward name)
    return _lazy_getattr(name)


__all__ = [
    "FilterInfo",
    "FilterSettings",
    "GreedyPolicy",
    "LoadedValueFunction",
    "MinimumOf",
    "OptimalPolicy",
    "RolloutResult",
    "RolloutSettings",
    "RolloutStore",
    "SafetyFilter",
    "SafetyFilterParallelWrapper",
    "SafetyFilterVectorWrapper",
    "SafetyFilterWrapper",
    "VerifySettings",
    "as_value_function",
    "export_filter",
    "load_value_function",
    "rollout",
    "sample_states",
    "sample_superlevel_set",
    "scenario_epsilon",
    "value_and_gradient",
    "verify",
    "violation_statistics",
    "wilson_interval",
    "worst_case_disturbance",
]
