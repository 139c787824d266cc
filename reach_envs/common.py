"""Deprecated: split into :mod:`reach_envs.spaces` (spaces and input checks) and
:mod:`reach_envs.views` (renderers, frames, trails); this path is removed in reach 0.3."""

from reach.deprecation import split

split(__name__)
