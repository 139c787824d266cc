"""The points a failed rollout refutes: where a value function's own policy was seen to fail.

A rollout under the policy a value function induces starts at ``(x0, T)`` and, at step ``k``, decides
at ``(x_k, T - k dt)`` with the same value function. If it fails at time ``tau`` (collides, or for
reach kinds has not reached the target by the horizon), the rest of the same rollout, from any
``(x_k, T - k dt)`` with ``k dt < tau``, is the policy's rollout from there, and fails too. So every
such point is one where the value function must not claim success (``V > 0`` for avoid, ``V < 0``
for reach kinds) if its claims are to hold under its own policy: a bound on the claim, not on the
true value, which another policy may achieve.

:func:`refuted_points` reads them off recorded rollouts (``rollout(..., record=True)``), a few per
failed trajectory, at the policy's decision instants (a policy that holds its input for several
steps decides only at the start of each hold). ``studies.train_until`` trains on them.
"""

from __future__ import annotations

import torch

from reach.value_function import ValueFunction
from safety.verification.rollout import RolloutResult, RolloutSettings, rollout

__all__ = ["recorded_refuted_points", "refuted_points"]


def refuted_points(
    result: RolloutResult, settings: RolloutSettings, per_trajectory: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(x (M, n), t (M,))``: up to ``per_trajectory`` points along each failed trajectory of
    ``result`` (recorded under ``settings``, whose horizon and step it was run with), evenly spaced
    over the decision instants before its failure, with their times-to-go. A trajectory that starts
    failed gives none."""
    traj = result.trajectories
    if traj is None:
        raise ValueError("refuted_points needs a recorded rollout (rollout(..., record=True))")
    if isinstance(per_trajectory, bool) or not isinstance(per_trajectory, int) or per_trajectory < 1:
        raise ValueError(f"per_trajectory must be a positive integer, got {per_trajectory!r}")
    if settings.horizon is None:
        raise ValueError("refuted_points needs the settings' horizon (RolloutSettings.for_system)")
    horizon, dt = float(settings.horizon), float(settings.dt)
    hold = 1 if settings.control_period is None else round(settings.control_period / dt)
    failed = torch.nonzero(result.failed).squeeze(-1)
    # decision instants before each failure: k = 0, hold, 2 hold, ... with k dt < the failure time
    end = result.decided_time[failed]
    count = torch.ceil(end / (dt * hold) - 1e-9).clamp(min=0).long()
    j = torch.arange(per_trajectory)
    # (F, per): evenly over each one's instants; fewer instants than asked: each once
    spread = (j[None, :] * count[:, None]) // per_trajectory
    k = (torch.where(count[:, None] >= per_trajectory, spread, j[None, :]) * hold).clamp(max=traj.shape[0] - 1)
    keep = j[None, :] < count[:, None]
    rows = failed[:, None].expand_as(k)
    x = traj[k[keep], rows[keep]]
    t = (horizon - k[keep].double() * dt).clamp(min=0.0).to(x.dtype)
    return x, t


def recorded_refuted_points(
    value_function: ValueFunction,
    states: torch.Tensor,
    settings: RolloutSettings,
    per_trajectory: int,
    device: str | torch.device | None = None,
    chunk: int = 1024,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`refuted_points` of ``states`` rolled out again under ``settings`` with their
    trajectories recorded, ``chunk`` states at a time (a recording holds every step of every state).
    Only the trajectories that fail in this rollout give points."""
    n = states.shape[-1]
    xs, ts = [torch.zeros(0, n)], [torch.zeros(0)]
    for lo in range(0, states.shape[0], chunk):
        result = rollout(value_function, states[lo : lo + chunk], settings, record=True, device=device, progress=False)
        x, t = refuted_points(result, settings, per_trajectory)
        xs.append(x.float().cpu())
        ts.append(t.float().cpu())
    x, t = torch.cat(xs), torch.cat(ts)
    if not bool(torch.isfinite(x).all()):
        raise ValueError("refuted points: a recorded rollout holds a non-finite state")
    return x, t
