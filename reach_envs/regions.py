"""The sets a scene's episodes are judged by, derived from the system's margins and declared nowhere else.

Each kind of problem (:mod:`reach.systems.problem`) names its sets by the margins the system writes:

=============  ==============================================  ==========================================
kind           regions (in drawing order)                      an episode ends (besides the time limit)
=============  ==============================================  ==========================================
avoid          ``failure set`` ``{l <= 0}`` (failure margin)   in the failure set (a collision)
reach          ``goal`` ``{l <= 0}`` (target margin)           in the goal (success)
reach-avoid    ``goal`` ``{l <= 0}``, then ``obstacles``       in an obstacle (a collision, even inside
               ``{g <= 0}`` (constraint margin)                the goal), else in the goal (success)
=============  ==============================================  ==========================================

A :class:`Region` holds the system's bound margin method, not a copy of the set, so a scene, its
environments and its renderer always agree with the system. The outcomes of a reach-kind episode
and the reward of the step that ends it are here too, in one table (:data:`OUTCOME_REWARDS`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from reach.systems.arrays import Backend, Column
from reach.systems.base import ControlAffineSystem

#: names of the regions, as :attr:`Region.name` spells them
FAILURE_SET, GOAL, OBSTACLES = "failure set", "goal", "obstacles"

#: outcomes of a reach-kind episode, as ``info["outcome"]`` reports them on the step that ends it
REACHED, COLLIDED, OUT_OF_ARENA, TIMEOUT = "reached", "collided", "out_of_arena", "timeout"
OUTCOMES = (REACHED, COLLIDED, OUT_OF_ARENA, TIMEOUT)
#: reward of the step that ends a reach-kind episode in each outcome; every other step earns 0
OUTCOME_REWARDS = {REACHED: 1.0, COLLIDED: -1.0, OUT_OF_ARENA: 0.0, TIMEOUT: 0.0}


def episode_outcome(collision: bool, reached: bool, out_of_arena: bool, timeout: bool) -> str | None:
    """The outcome of a reach-kind step, first match wins: a collision, the goal (reached only outside
    obstacles), leaving the arena, the time limit; ``None`` while the episode runs on."""
    if collision:
        return COLLIDED
    if reached:
        return REACHED
    if out_of_arena:
        return OUT_OF_ARENA
    return TIMEOUT if timeout else None


@dataclass(frozen=True)
class Region:
    """The states ``{margin(x) <= 0}`` for one of the system's margins (``margin_columns(x, xp)``)."""

    name: str
    margin_columns: Callable[[Sequence[Column], Backend], Column]

    def contains(self, x: Sequence[Column], xp: Backend) -> Column:
        """Whether the states (columns on backend ``xp``) lie in the region (closed: margin ``<= 0``)."""
        return self.margin_columns(x, xp) <= 0.0


def goal_region(system: ControlAffineSystem) -> Region | None:
    """The target set of a reach kind (target margin ``<= 0``); ``None`` for an avoid system."""
    return Region(GOAL, system.target_margin_columns) if system.problem.reaches else None


def obstacle_region(system: ControlAffineSystem) -> Region | None:
    """The obstacles of a reach-avoid system (constraint margin ``<= 0``); ``None`` for the other kinds."""
    return Region(OBSTACLES, system.constraint_margin_columns) if system.problem.has_constraint else None


def system_regions(system: ControlAffineSystem) -> tuple[Region, ...]:
    """The regions of the table above, in drawing order (obstacles over the goal: a state in both
    counts as a collision)."""
    if not system.problem.reaches:
        return (Region(FAILURE_SET, system.failure_margin_columns),)
    obstacles = obstacle_region(system)
    return (goal_region(system),) if obstacles is None else (goal_region(system), obstacles)


__all__ = [
    "COLLIDED",
    "FAILURE_SET",
    "GOAL",
    "OBSTACLES",
    "OUTCOMES",
    "OUTCOME_REWARDS",
    "OUT_OF_ARENA",
    "REACHED",
    "TIMEOUT",
    "Region",
    "episode_outcome",
    "goal_region",
    "obstacle_region",
    "system_regions",
]
