"""Safety: optimal policies from grad V, a least-restrictive filter, rollouts and verification.

Everything here takes a :class:`~reach.value_function.ValueFunction` (a trained
network, a DeepReach import or a grid solution; :func:`load_value_function` loads any of them):

* :class:`OptimalPolicy` - ``u*``, ``d*`` from the gradient through the system's derived functions;
* :class:`SafetyFilter` and its environment adapters (:mod:`safety.wrappers`);
* :func:`rollout` - batched closed-loop simulation that skips decided trajectories;
* :func:`verify`, :func:`evaluate_many` - violation statistics, delta-level, scenario guarantee,
  across many checkpoints on the same states.
"""

from reach.value_function import MinimumOf, value_and_gradient
from safety.evaluate import evaluate_many, load_results, markdown_table
from safety.filter import FilterInfo, SafetyFilter
from safety.metrics import scenario_epsilon, violation_statistics, wilson_interval
from safety.policy import OptimalPolicy
from safety.rollout import RolloutResult, rollout
from safety.value_functions import LoadedValueFunction, as_value_function, load_value_function
from safety.verify import VerifySettings, sample_states, sample_superlevel_set, verify
from safety.wrappers import SafetyFilterParallelWrapper, SafetyFilterVectorWrapper, SafetyFilterWrapper

__all__ = [
    "FilterInfo",
    "LoadedValueFunction",
    "MinimumOf",
    "OptimalPolicy",
    "RolloutResult",
    "SafetyFilter",
    "SafetyFilterParallelWrapper",
    "SafetyFilterVectorWrapper",
    "SafetyFilterWrapper",
    "VerifySettings",
    "as_value_function",
    "evaluate_many",
    "load_results",
    "load_value_function",
    "markdown_table",
    "rollout",
    "sample_states",
    "sample_superlevel_set",
    "scenario_epsilon",
    "value_and_gradient",
    "verify",
    "violation_statistics",
    "wilson_interval",
]
