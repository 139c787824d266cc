"""How the grid solver computes: its accuracy and time-stepping options in one frozen value.

The pattern of hj_reachability's ``SolverSettings``: the scheme's choices travel together, their
defaults live in one place (the library, the ``reach groundtruth`` command and its help text all
read them from here), and a bad choice is refused when the settings are made, before any grid is
allocated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

#: Above this CFL number TVD-RK3 with WENO5 is not guaranteed stable (the scheme's linear limit is ~1).
CFL_STABLE = 1.0

#: how the solver enforces the problem after each step (see :attr:`SolverSettings.tube`)
TUBES = ("min_with_target", "min_over_time", "set")

#: the Lax-Friedrichs dissipation choices (see :attr:`SolverSettings.dissipation`)
DISSIPATIONS = ("local", "global")


@dataclass(frozen=True)
class SolverSettings:
    """Accuracy and time-stepping options of :func:`groundtruth.solve`, checked at construction.

    Attributes:
        cfl: Courant number in ``(0, 1]``; values above 1 are refused (TVD-RK3 + WENO5 is unstable
            there).
        dissipation: ``"local"`` (default) uses each node's own bound on ``|dH/dp_i|`` over the
            whole input box; ``"global"`` uses the largest bound over the grid everywhere (more
            diffusive and farther from the MATLAB toolbox; measured: docs/results/groundtruth.md).
        tube: how the tube is enforced after each step. ``"min_with_target"`` (default) is the
            variational inequality ``V <- min(V, l)`` (DeepReach's form). ``"min_over_time"`` is
            the MATLAB toolbox's ``minVOverTime``, ``V <- min(V_new, V_old)``: the same exact
            solution, but numerically monotone in time; with ``min_with_target`` numerical
            diffusion at kinks of ``V`` can raise ``V`` slightly between output times.
            ``"set"`` solves the backward reachable *set* instead of the tube: no minimum with
            ``l``, so ``V(x, t) <= 0`` means "in the set exactly at time ``t``" (reach at ``t``, or
            fail at ``t``). For reach-avoid every option then applies ``V <- max(V, -g)``.
        dtype: a floating torch dtype for the computation (float32 by default, float64 for
            references).
        device: where the computation runs (a torch device or its name).
        compile: fuse the right-hand side with ``torch.compile``. ``None`` (default) decides from
            the work: on CPU, compile for at least
            :data:`groundtruth.solver.COMPILE_MIN_NODE_UPDATES` node updates (falling back to eager
            mode if compiling fails); on other devices stay eager (compiling did not pay off there;
            measured: docs/results/groundtruth.md).
    """

    cfl: float = 0.75
    dissipation: Literal["local", "global"] = "local"
    tube: Literal["min_with_target", "min_over_time", "set"] = "min_with_target"
    dtype: torch.dtype = torch.float32
    device: torch.device | str = "cpu"
    compile: bool | None = None

    def __post_init__(self) -> None:
        cfl = self.cfl
        if isinstance(cfl, bool) or not isinstance(cfl, (int, float)):
            raise ValueError(f"cfl must be a number in (0, {CFL_STABLE}], got {cfl!r}")
        if not (math.isfinite(cfl) and 0 < cfl <= CFL_STABLE):
            raise ValueError(
                f"cfl={cfl} is outside (0, {CFL_STABLE}]: TVD-RK3 with WENO5 is only stable "
                "up to a Courant number of about 1"
            )
        if self.dissipation not in DISSIPATIONS:
            raise ValueError(f"dissipation must be 'global' or 'local', got {self.dissipation!r}")
        if self.tube not in TUBES:
            raise ValueError(f"tube must be one of {TUBES}, got {self.tube!r}")
        if not isinstance(self.dtype, torch.dtype) or not self.dtype.is_floating_point:
            raise ValueError(f"dtype must be a floating torch dtype such as torch.float32, got {self.dtype!r}")
        if not isinstance(self.device, (str, torch.device)):
            raise ValueError(f"device must be a torch device or its name, got {self.device!r}")
        try:
            torch.device(self.device)
        except RuntimeError:
            raise ValueError(f"device {self.device!r} is not a torch device (e.g. 'cpu', 'cuda', 'cuda:1')") from None
        if not isinstance(self.compile, (bool, type(None))):
            raise ValueError(f"compile must be True, False or None (decide from the work), got {self.compile!r}")
