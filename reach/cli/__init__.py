"""Deprecated alias of :mod:`reach_cli` (moved there; this path is removed in reach 0.3)."""

from reach.deprecation import moved

moved(
    __name__,
    submodules=(
        "common",
        "demo",
        "envs",
        "evaluate",
        "filter_eval",
        "groundtruth",
        "plot",
        "pretrained",
        "record",
        "sweep",
        "train",
    ),
)
