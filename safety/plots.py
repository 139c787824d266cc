"""Deprecated alias of :mod:`studies.plots` (moved there; this path is removed in reach 0.3)."""

from reach.deprecation import moved

moved(__name__)
