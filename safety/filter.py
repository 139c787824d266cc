"""The least-restrictive safety filter: keep the nominal input unless the value says danger.

``SafetyFilter(vf, threshold)(x, t, u_nominal) -> (u, info)`` keeps ``u_nominal`` where
``V(x, t) > threshold`` and applies the optimal control ``u*(x, t)`` elsewhere, batched over states.
The time-to-go ``t`` is the caller's choice; the environment adapters in :mod:`safety.wrappers`
default to a *fixed horizon* (``t`` = the system's horizon, the tube the network was trained for):
a state is filtered when it cannot be kept safe for that long. ``"remaining"`` uses the time left in
the episode instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from reach.value_function import ValueFunction
from safety.policy import OptimalPolicy, check_states


@dataclass
class FilterInfo:
    """What the filter saw and did, per state: value, nominal and applied input, intervention."""

    value: torch.Tensor
    nominal: torch.Tensor
    applied: torch.Tensor
    intervened: torch.Tensor


class SafetyFilter:
    """Least-restrictive filter around a value function (see the module docstring).

    Args:
        value_function: any :class:`ValueFunction` (network, DeepReach import, grid solution).
        threshold: intervene where ``V <= threshold`` (a small positive margin buys robustness to
            sampling and value errors).
    """

    def __init__(self, value_function: ValueFunction, threshold: float = 0.0) -> None:
        if not isinstance(threshold, (int, float)) or not math.isfinite(threshold):
            raise ValueError(f"threshold must be a finite number, got {threshold!r}")
        self.value_function = value_function
        self.system = value_function.system
        self.threshold = float(threshold)
        self.policy = OptimalPolicy(value_function)

    def __call__(
        self, x: torch.Tensor, t: float | torch.Tensor, u_nominal: torch.Tensor
    ) -> tuple[torch.Tensor, FilterInfo]:
        """Filtered inputs ``(..., m_u)`` for states ``(..., n)`` and nominal inputs ``(..., m_u)``.

        Nominal inputs are physical units; where kept they are returned bit for bit, where
        replaced the result is exactly ``u*``. NaN/inf in states or nominal inputs, a time-to-go the value
        function does not cover, and a non-finite value or ``u*`` raise ``ValueError``: the filter
        never passes the nominal input on a value it cannot trust.
        """
        system = self.system
        check_states(x, system.state_dim)
        if not isinstance(u_nominal, torch.Tensor) or u_nominal.shape != (*x.shape[:-1], system.control_dim):
            shape = tuple(u_nominal.shape) if isinstance(u_nominal, torch.Tensor) else type(u_nominal).__name__
            raise ValueError(f"u_nominal must have shape {(*x.shape[:-1], system.control_dim)}, got {shape}")
        if not bool(torch.isfinite(u_nominal).all()):
            raise ValueError(f"u_nominal contains NaN or inf: {u_nominal[~torch.isfinite(u_nominal)][:4].tolist()}")
        value, u_star, _ = self.policy.inputs(x, t)
        # fail closed: a NaN value compares False with everything, so "not above the threshold" (never
        # "at or below it") decides; and an untrustworthy value or input is refused outright
        intervene = ~(value > self.threshold)
        untrusted = ~torch.isfinite(value) | ~torch.isfinite(u_star).all(-1)
        if bool(untrusted.any()):
            bad = x[untrusted][0].tolist()
            raise ValueError(
                f"value function returned a non-finite value or optimal input at state {bad} (t = {t}); "
                "the filter does not trust it and keeps no nominal input"
            )
        u_nominal = u_nominal.to(u_star.dtype)
        applied = torch.where(intervene.unsqueeze(-1), u_star, u_nominal)
        return applied, FilterInfo(value=value, nominal=u_nominal, applied=applied, intervened=intervene)
