"""Run-time safety filters: keep the nominal input unless the value function says danger.

* :mod:`safety.filters.settings` - :class:`~safety.filters.settings.FilterSettings`, the options that
  travel together (kind, threshold, time-to-go, gamma, backup horizon and disturbance, policy);
* :mod:`safety.filters.base` - :class:`~safety.filters.base.SafetyFilter`, batched over states: the
  one entry point, and what every kind shares;
* :mod:`safety.filters.switch`, :mod:`safety.filters.lookahead`, :mod:`safety.filters.smooth` - the
  three kinds, each its own decision rule (what each does, and when to use it);
* :mod:`safety.filters.wrappers` - the Gymnasium, vector and PettingZoo adapters;
* :mod:`safety.filters.export` - a filter as one ONNX file for the torch-free :mod:`reach_runtime`.
"""

# each kind registers with SafetyFilter as its module loads: loaded here, every kind is there for
# SafetyFilter(vf, kind=...) whichever module of the package a caller imports
from safety.filters import lookahead, smooth, switch

__all__ = ["lookahead", "smooth", "switch"]
