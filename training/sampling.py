"""The points each training step draws, all from one generator so that a resumed run replays the same stream.

The draws come in a fixed order (labels when due, then the uniform points, then the zero-level
candidates), so a resumed run draws what an uninterrupted run would have drawn; only a move to
another kind of device restarts the stream (:func:`moved_run_seed`).
"""

from __future__ import annotations

import torch

from training.config import TrainConfig
from training.labels import mpc_lower_bound, policy_lower_bound
from training.network import LEARNED_BOUNDARY, ValueNetwork

#: the lower-bound term's labelled points ``(x, t, J)``
Labels = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def moved_run_seed(seed: int, step: int) -> int:
    """The sampling generator's seed for a run resumed on another kind of device at ``step``: a CPU
    generator's state cannot seed a CUDA one or back, so the stream restarts from the run's seed and
    step (deterministic: two resumes of the same checkpoint on the same device draw the same points)."""
    return (seed * 1_000_003 + step) % (2**63)


class PointSampler:
    """Draws a run's training points on ``device`` from its own generator, seeded with ``config.seed``."""

    def __init__(self, config: TrainConfig, network: ValueNetwork, device: torch.device) -> None:
        self.config = config
        self.network = network
        self.device = device
        self.generator = torch.Generator(device=device)
        self.generator.manual_seed(config.seed)
        box = network.system.domain_tensor(torch.float32, device)
        self._low, self._span = box[:, 0], box[:, 1] - box[:, 0]

    def uniform(self, n: int, tmax: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` states uniform on the domain and times uniform on ``[0, tmax]``, from the run's generator
        (states first: resumed runs replay the same stream)."""
        g = self.generator
        x = self._low + torch.rand((n, self.network.system.state_dim), generator=g, device=self.device) * self._span
        return x, torch.rand(n, generator=g, device=self.device) * tmax

    def points(self, tmax: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """One step's ``config.points`` states and times, and the vanilla parameterisation's boundary
        mask (its first ``boundary_fraction`` of points, at ``t = 0``; ``None`` otherwise)."""
        c = self.config
        n = c.points
        x, t = self.uniform(n, tmax)
        mask = None
        if c.parameterisation in LEARNED_BOUNDARY:
            mask = torch.zeros(n, dtype=torch.bool, device=self.device)
            mask[: int(c.boundary_fraction * n)] = True
            t = torch.where(mask, torch.zeros_like(t), t)
        near = int(c.zero_level_fraction * n)
        if near:  # the last points (never the vanilla boundary's first ones): nearest V = 0 of a larger draw
            x[n - near :], t[n - near :] = self.near_zero_level(near, tmax)
        return x, t, mask

    def near_zero_level(self, count: int, tmax: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` states and times with the smallest ``|V|`` among ``zero_level_candidates x count``
        uniform draws (one forward pass without gradients)."""
        m = count * self.config.zero_level_candidates
        x, t = self.uniform(m, tmax)
        with torch.no_grad():
            keep = self.network(x, t).abs().topk(count, largest=False).indices
        return x[keep], t[keep]

    def lower_bound_labels(self, tmax: float) -> Labels:
        """Fresh states and times labelled with what the network's policy achieves (``J <= V``), by the
        ``config.lower_bound`` rule (``"mpc"`` or ``"policy"``)."""
        c = self.config
        x, t = self.uniform(c.lower_bound_points, tmax)
        if c.lower_bound == "mpc":
            floor = mpc_lower_bound(
                self.network,
                x,
                t,
                c.lower_bound_dt,
                c.lower_bound_horizon,
                c.lower_bound_samples,
                c.lower_bound_noise,
                self.generator,
            )
        else:
            floor = policy_lower_bound(self.network, x, t, c.lower_bound_dt)
        return x, t, floor

    def resume_stream(self, state: torch.Tensor, trained_on: str, step: int) -> bool:
        """Continue a checkpoint's stream: its generator ``state`` if it was drawn on this kind of device
        (``trained_on``), else reseed from :func:`moved_run_seed` at ``step``. Returns whether the stream
        was reseeded (the caller says so: the points differ from an uninterrupted run's)."""
        if trained_on == self.device.type:
            self.generator.set_state(state)
            return False
        self.generator.manual_seed(moved_run_seed(self.config.seed, step))
        return True
