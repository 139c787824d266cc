"""Safety core: optimal policies from grad V, a least-restrictive filter, rollouts and verification.

This is the layer above training; batch evaluation tables, filter studies, plots and the demo sit
one floor up, in :mod:`studies`.

Everything here takes a :class:`~reach.value_function.ValueFunction` (a trained
network, a DeepReach import or a grid solution; :func:`load_value_function` loads any of them):

* :class:`OptimalPolicy` - ``u*``, ``d*`` from the gradient through the system's derived functions;
* :class:`GreedyPolicy` - the candidate input held for a short step that leaves the most value (the
  switch filter's default backup input; ``rollout(..., policy="greedy")``);
* :class:`SafetyFilter` and its environment adapters (:mod:`safety.filters.wrappers`), which take one
  :class:`FilterSettings` (kind, threshold, time-to-go, gamma, backup horizon and disturbance, policy);
* :func:`rollout` - batched closed-loop simulation that skips decided trajectories;
* :func:`verify` - violation statistics, delta-level and the scenario guarantee of one value
  function (:func:`studies.evaluate_many` runs it across many checkpoints on the same states);
* :class:`RolloutStore` - rollout outcomes kept block by block, so a long verification resumes;
* :func:`export_filter` - a filter as one ONNX file for the torch-free :mod:`reach_runtime`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from reach.lazy import lazy_exports
from reach.value_function import MinimumOf, value_and_gradient
from safety.filters.base import FilterInfo, SafetyFilter
from safety.filters.settings import FilterSettings
from safety.value_loading import LoadedValueFunction, as_value_function, load_value_function
from safety.value_policies import GreedyPolicy, OptimalPolicy, worst_case_disturbance
from safety.verification.metrics import scenario_epsilon, violation_statistics, wilson_interval
from safety.verification.rollout import RolloutResult, RolloutSettings, rollout
from safety.verification.rollout_store import RolloutStore
from safety.verification.verify import VerifySettings, sample_states, sample_superlevel_set, verify

if TYPE_CHECKING:
    from safety.filters.export import export_filter
    from safety.filters.wrappers import SafetyFilterParallelWrapper, SafetyFilterVectorWrapper, SafetyFilterWrapper

#: names whose module loads Gymnasium and PettingZoo (the wrappers) or the ONNX export, imported on first
#: use so that ``import safety.filters.base`` (the CLI's start-up) stays light. (A name that equals its module's,
#: like ``rollout`` and ``verify``, must stay eager: importing the submodule would shadow it.)
_LAZY = {
    "SafetyFilterParallelWrapper": "safety.filters.wrappers",
    "SafetyFilterVectorWrapper": "safety.filters.wrappers",
    "SafetyFilterWrapper": "safety.filters.wrappers",
    "export_filter": "safety.filters.export",
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)


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
