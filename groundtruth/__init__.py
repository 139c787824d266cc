"""Ground truth: a level-set HJI solver in torch for systems with up to 4 dimensions.

``solve(system, grid, times)`` returns a :class:`GridSolution` that implements the value-function
interface (value and gradient at batched states and times) and saves to a self-describing ``.npz``.
"""

from groundtruth.grid import Grid
from groundtruth.solution import GridSolution
from groundtruth.solver import solve

__all__ = ["Grid", "GridSolution", "solve"]
