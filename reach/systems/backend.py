"""Deprecated alias of :mod:`reach.systems.arrays` (moved there; this path is removed in reach 0.3)."""

from reach.deprecation import moved

moved(__name__)
