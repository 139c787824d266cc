"""Run-time safety filters: keep the nominal input unless the value function says danger.

* :mod:`safety.filters.settings` - :class:`~safety.filters.settings.FilterSettings`, the options that
  travel together (kind, threshold, time-to-go, gamma, backup horizon and disturbance, policy);
* :mod:`safety.filters.filter` - :class:`~safety.filters.filter.SafetyFilter`, batched over states;
* :mod:`safety.filters.wrappers` - the Gymnasium, vector and PettingZoo adapters;
* :mod:`safety.filters.export` - a filter as one ONNX file for the torch-free :mod:`reach_runtime`.
"""
