"""Ground truth: a level-set HJI solver in torch for systems with up to 4 dimensions.

``solve(system, grid, times, settings=SolverSettings(...))`` returns a :class:`GridSolution` that
implements the value-function interface (value and gradient at batched states and times) and saves
to a self-describing ``.npz``; :class:`SolverSettings` holds the scheme's options and their defaults.
"""

from groundtruth.grid import Grid
from groundtruth.settings import SolverSettings
from groundtruth.solution import GridSolution
from groundtruth.solver import solve

__all__ = ["Grid", "GridSolution", "SolverSettings", "solve"]
