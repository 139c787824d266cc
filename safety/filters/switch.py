"""The switch filter (least-restrictive): keep the nominal input while the value says safe.

``SafetyFilter(vf, threshold, kind="switch")`` (the default kind) keeps ``u_nominal`` where
``V(x, t) > threshold``, else applies the backup input. It decides on the current state alone, one
value-and-gradient evaluation per decision, so it is the cheapest kind and the one to start with.

Its limit is the step: between two decisions of a zero-order-hold controller ``V`` can fall by
about ``|dl/dt|_max dt``, so at threshold 0 a state riding the set's boundary can slip across it
between decisions. The env adapters' default threshold (``2 * rate * dt``,
:func:`~safety.filters.settings.default_threshold`) covers that; where even a small margin is too
conservative, the lookahead (:mod:`safety.filters.lookahead`) checks the step itself instead.

The backup input defaults to the greedy input (``policy="greedy"``,
:class:`~safety.value_policies.GreedyPolicy`): the switch pays for it only where it intervenes, and
where ``grad V`` blends two manoeuvres (several cars converging) the greedy input commits to one
where ``u*`` can steer into both (measured: docs/results/filters.md). ``policy="gradient"`` applies
``u*``.

Reach kinds (``"reach"``, ``"reach-avoid"``; :mod:`safety.filters.base`): the switch keeps
``u_nominal`` where ``V(x, t) < -threshold`` (the task stays feasible with a margin), else applies
``u*``; once the time-to-go has run out (``t <= 0``) nothing is certified and ``u*`` is applied.
"""

from __future__ import annotations

import torch

from safety.filters.base import Evaluation, SafetyFilter

__all__ = ["SwitchFilter"]


class SwitchFilter(SafetyFilter, kind="switch"):
    """The switch filter (see the module docstring); made by ``SafetyFilter(vf, kind="switch")``."""

    def _choose(
        self, x: torch.Tensor, t: float | torch.Tensor, u_nominal: torch.Tensor, seen: Evaluation, trusted: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, None]:
        # a NaN value compares False with everything: "not above" (never "at or below") decides;
        # oriented, "> threshold" is the good side of every kind (V > thr avoid, V < -thr reach)
        keep = (self.problem.orient(seen.value) > self.threshold) & self._time_left(t, 0.0, seen.value) & trusted
        backup = self._backup_input(x, t, seen.u_star, seen.d_star, ~keep)
        return keep, torch.where(keep.unsqueeze(-1), u_nominal, backup), None
