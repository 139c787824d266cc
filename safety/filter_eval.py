"""Deprecated alias of :mod:`studies.filter_eval` (moved there; this path is removed in reach 0.3)."""

from reach.deprecation import moved

moved(__name__)
