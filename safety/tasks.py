"""Deprecated alias of :mod:`studies.tasks` (moved there; this path is removed in reach 0.3)."""

from reach.deprecation import moved

moved(__name__)
