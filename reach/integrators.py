"""Fixed-step integrators on columns, shared by every backend (floats, NumPy, torch).

The one implementation of explicit Euler and RK4 in the package: environments step with it on
Python floats or NumPy columns, and the rollout engine on torch columns. Inputs are held constant
over a step (zero-order hold), as a digital controller applies them. Periodic dimensions are
wrapped after the step, not inside it, so RK4 stages see continuous angles. A system with state
limits that its inputs respect (:mod:`reach.systems.limits`) has each step saturated to them, as the
continuous system keeps them; any other system steps with no extra work.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from reach.systems.arrays import Backend, Column
from reach.systems.base import ControlAffineSystem

INTEGRATORS = ("rk4", "euler")

Stepper = Callable[[Sequence[Column], Sequence[Column], Sequence[Column]], list[Column]]


def check_integrator(integrator: str) -> str:
    """``integrator`` if it is one of :data:`INTEGRATORS`, else ``ValueError`` naming it."""
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    return integrator


def make_stepper(system: ControlAffineSystem, dt: float, integrator: str, xp: Backend) -> Stepper:
    """A function ``(x, u, d) -> x_next`` advancing ``dt`` seconds, wrapping headings and keeping the
    system's state limits (:meth:`~reach.systems.limits.StateLimits.saturate_columns`), if it has any.

    ``x``, ``u`` and ``d`` are column sequences of the backend ``xp``.
    """
    step = _unlimited_stepper(system, dt, check_integrator(integrator), xp)
    if not system.state_limits():
        return step  # the default: the dynamics' step as it is, no extra work
    saturate = system.saturate_columns

    def limited(x: Sequence[Column], u: Sequence[Column], d: Sequence[Column]) -> list[Column]:
        return saturate(x, step(x, u, d), xp)

    return limited


def _unlimited_stepper(system: ControlAffineSystem, dt: float, integrator: str, xp: Backend) -> Stepper:
    """Euler or RK4 over ``dt``, headings wrapped after the step."""
    xdot = system.xdot_columns
    wrap = system.wrap_columns
    if integrator == "euler":

        def euler(x: Sequence[Column], u: Sequence[Column], d: Sequence[Column]) -> list[Column]:
            k = xdot(x, u, d, xp)
            return wrap([a + dt * b for a, b in zip(x, k)], xp)

        return euler

    half, sixth = 0.5 * dt, dt / 6.0

    def rk4(x: Sequence[Column], u: Sequence[Column], d: Sequence[Column]) -> list[Column]:
        k1 = xdot(x, u, d, xp)
        k2 = xdot([a + half * b for a, b in zip(x, k1)], u, d, xp)
        k3 = xdot([a + half * b for a, b in zip(x, k2)], u, d, xp)
        k4 = xdot([a + dt * b for a, b in zip(x, k3)], u, d, xp)
        return wrap([a + sixth * (b1 + 2.0 * b2 + 2.0 * b3 + b4) for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4)], xp)

    return rk4
