"""Deprecated alias of :mod:`studies.sweeps` (moved there; this path is removed in reach 0.3)."""

from reach.deprecation import moved

moved(__name__, submodules=("backends", "report", "scoring", "spec", "sweep", "task"))
