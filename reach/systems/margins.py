"""What a system knows of how fast its failure margin can change: declared bounds and a sampled estimate.

Rollouts stop simulating trajectories whose failure set is out of reach (:meth:`MarginBounds.margin_floor`),
or, for reach kinds, whose target is (:meth:`MarginBounds.target_floor`);
formal certificates treat states far from failure without bounding the network there
(:meth:`MarginBounds.margin_step_bound`, :meth:`MarginBounds.margin_outside_domain`), and filters
set default thresholds from :meth:`MarginBounds.margin_rate_estimate`.

Why a module of its own: these are proof obligations and estimates about the margin, declared per
system (the defaults here know nothing), apart from the physics declarations of
:class:`~reach.systems.base.ControlAffineSystem`, which inherits :class:`MarginBounds`.
"""

from __future__ import annotations

from typing import Any

import torch

from reach.systems.arrays import TORCH
from reach.systems.box import Ball


class MarginBounds:
    """Bounds and estimates of the failure margin's change for a
    :class:`~reach.systems.base.ControlAffineSystem`; a system overrides the bounds it can prove."""

    def margin_rate_bound(self) -> float | None:
        """A bound on ``|d l(x(t)) / dt|`` along every trajectory with admissible inputs, or ``None``.

        Physics, declared per system where it is known (e.g. the sum of two cars' speeds bounds how
        fast their distance changes). With it, a rollout can stop simulating a trajectory once
        ``l(x) > bound * time_left``: the failure set is then out of reach, whatever the inputs.
        """
        return None

    def target_floor(self, x: torch.Tensor, time: float) -> torch.Tensor | None:
        """A lower bound of the target margin over the next ``time`` seconds from states ``x``
        ``(..., n)`` (reach kinds), under *any* admissible inputs and disturbances, held over Euler or
        RK4 steps or not; ``None`` (the default) where none is known.

        A proof obligation, declared per system with its argument in the docstring (and checked at
        samples in the tests). A reach rollout stops a trajectory whose floor over the time left is
        positive: the target is out of reach, so the trajectory has failed. A reach-avoid rollout stops
        it only where :meth:`margin_floor` (of the constraint) is positive too, so the constraint
        violations it counts stay the same."""
        return None

    def margin_step_bound(self, dt: float, integrator: str) -> float | None:
        """``delta``: one step of ``integrator`` over ``dt`` lowers the failure margin by at most this,
        from *every* state (inside the domain or far outside it), with every admissible control and
        disturbance held over the step: ``l(step(x, u, d)) >= l(x) - delta``. ``None`` (the default)
        where no such bound is known for this integrator.

        A proof obligation, declared per system with its argument in the docstring (and checked at
        samples in the tests): a formal certificate (:mod:`safety.formal.verifier`) uses it to treat the
        states far from failure, where the value function is not trusted or not defined, without
        bounding the network there."""
        return None

    def margin_outside_domain(self, scale: float = 1.0) -> float | None:
        """A lower bound of the failure margin ``l`` on every state outside the domain (its periodic
        dimensions aside), or ``None`` (the default) where a state outside may be near failure.
        ``scale``: outside the domain widened that many times about its centre (a certificate's
        ``closure_scale``). With :meth:`margin_step_bound` it lets a certificate accept next states
        that leave the domain."""
        return None

    def certification_defaults(self) -> dict[str, Any] | None:
        """The proof settings ``reach certify`` uses for this system when given none: a mapping of
        :class:`~safety.formal.settings.CertifySettings` fields (``level``, ``escape_margin``,
        ``closure_scale``, ``closure_relative_width``, ``min_relative_width``, ``closure_refinements``),
        or ``None`` (the default): derived from the lemmas above
        (:func:`safety.formal.settings.certify_defaults`). A system states them beside its lemmas
        where it knows better settings than the derived ones."""
        return None

    def margin_floor(self, x: torch.Tensor, time: float) -> torch.Tensor | None:
        """A lower bound of ``l`` over the next ``time`` seconds from states ``x`` ``(..., n)``, under
        *any* admissible inputs (held over Euler steps or not), or ``None`` where none is known.

        Default: ``l(x) - margin_rate_bound() * time``. A system that knows more of its geometry may
        return a tighter bound (multi-vehicle systems use the cars' headings and turn rates). A
        rollout stops a trajectory whose floor over the time left is positive: no input can reach
        the failure set any more."""
        bound = self.margin_rate_bound()
        if bound is None:
            return None
        return self.failure_margin(x) - bound * time

    def margin_rate_estimate(self, samples: int = 4096, seed: int = 0) -> float:
        """The largest ``|d l(x(t)) / dt|`` over ``samples`` states drawn from the domain and every
        admissible input (exact over the input boxes: ``grad l . xdot`` is affine in the inputs).

        A sampled estimate, not a bound: it sets default filter thresholds for systems that declare
        no :meth:`margin_rate_bound`, and never licenses skipping simulation."""
        x = self.sample_states(samples, torch.Generator().manual_seed(seed), dtype=torch.float64).requires_grad_(True)
        (p,) = torch.autograd.grad(self.boundary_value(x).sum(), x)  # l, or max(l, -g): what V starts from
        x = x.detach()
        cols, pc = TORCH.unbind(x), TORCH.unbind(p)
        centre = self.xdot_columns(cols, self.control_bounds.center, self.disturbance_bounds.center, TORCH)
        rate = sum(pi * fi for pi, fi in zip(pc, centre)).abs()
        sides = [(self.control_matrix(cols, TORCH), self.control_bounds)]
        if self.disturbance_dim:
            sides.append((self.disturbance_matrix(cols, TORCH), self.disturbance_bounds))
        for matrix, box in sides:
            switching = self._switching(matrix, pc, box.dim)
            if isinstance(box, Ball):  # max over the ball of |s . (u - c)| is r |s|_2
                if any(isinstance(sj, torch.Tensor) for sj in switching):
                    rate = rate + box.radius * TORCH.norm(switching)
                continue
            for sj, hw in zip(switching, box.half_width):
                rate = rate + hw * (sj.abs() if isinstance(sj, torch.Tensor) else abs(sj))
        rate = rate[torch.isfinite(rate)]
        return float(rate.max()) if rate.numel() else 0.0
