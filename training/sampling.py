"""The points each training step draws, all from one generator so that a resumed run replays the same stream.

The draws come in a fixed order (labels when due, then the uniform points, then the zero-level
candidates), so a resumed run draws what an uninterrupted run would have drawn; only a move to
another kind of device, or to another number of processes, restarts the stream (:func:`moved_run_seed`).
Each process of a distributed run draws its own share of the points from its own stream
(:func:`rank_seed`).
"""

from __future__ import annotations

import math

import torch

from reach.systems import ControlAffineSystem
from training.config import TrainConfig
from training.loss import RefutedPoints
from training.network import LEARNED_BOUNDARY, ValueNetwork
from training.policy_lower_bounds import mpc_lower_bound, policy_lower_bound

#: the lower-bound term's labelled points ``(x, t, J)``
Labels = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def moved_run_seed(seed: int, step: int) -> int:
    """The sampling generator's seed for a run resumed on another kind of device at ``step``: a CPU
    generator's state cannot seed a CUDA one or back, so the stream restarts from the run's seed and
    step (deterministic: two resumes of the same checkpoint on the same device draw the same points)."""
    return (seed * 1_000_003 + step) % (2**63)


def rank_seed(seed: int, rank: int) -> int:
    """The sampling seed of process ``rank`` in a run of several processes: the run's ``seed`` itself for
    rank 0 (one process under torchrun draws what a plain run draws), and for the others ``seed`` plus
    ``rank`` times 2**64 over the golden ratio, modulo 2**63: for every rank below a million that lies
    outside the range of run seeds (0 to 2**32 - 1), so no process draws another run's rank-0 stream."""
    return (seed + rank * 0x9E37_79B9_7F4A_7C15) % (2**63)


def training_box(system: ControlAffineSystem) -> tuple[tuple[float, float], ...]:
    """The system's :meth:`~reach.systems.base.ControlAffineSystem.training_domain`, checked: finite,
    one ``(low, high)`` per state, and containing the domain (a box that leaves out states the network
    is asked about would train it elsewhere); a periodic dimension keeps its period."""
    box = tuple((float(lo), float(hi)) for lo, hi in system.training_domain())
    if len(box) != system.state_dim:
        raise ValueError(f"{system.name}: training_domain has {len(box)} dimensions, the state {system.state_dim}")
    for name, periodic, (lo, hi), (d_lo, d_hi) in zip(system.state_names, system.periodic, box, system.domain):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= d_lo and hi >= d_hi):
            raise ValueError(
                f"{system.name}: training_domain of {name} must be finite and contain the domain "
                f"[{d_lo}, {d_hi}], got [{lo}, {hi}]"
            )
        if periodic and (lo, hi) != (d_lo, d_hi):
            raise ValueError(f"{system.name}: periodic {name} trains on its period [{d_lo}, {d_hi}], got [{lo}, {hi}]")
    return box


class PointSampler:
    """Draws a run's training points on ``device`` from its own generator, seeded with ``config.seed``.

    In a run of ``world_size`` processes, the sampler of process ``rank`` draws ``1 / world_size`` of every
    step's points and lower-bound labels (their counts split evenly:
    :meth:`training.distributed.Processes.check_shares`), from :func:`rank_seed`'s stream."""

    def __init__(
        self, config: TrainConfig, network: ValueNetwork, device: torch.device, rank: int = 0, world_size: int = 1
    ) -> None:
        self.config = config
        self.network = network
        self.device = device
        self.world_size = world_size
        #: this process's sampling seed (the run's seed in a run of one process)
        self.seed = rank_seed(config.seed, rank)
        self.generator = torch.Generator(device=device)
        self.generator.manual_seed(self.seed)
        box = torch.tensor(training_box(network.system), dtype=torch.float32, device=device)
        self._low, self._span = box[:, 0], box[:, 1] - box[:, 0]
        self._hard_states: torch.Tensor | None = None
        self._refuted: RefutedPoints | None = None
        self.hard_fraction = 0.0
        #: how near: a uniform offset of up to this share of the box's side, per dimension
        self.hard_radius = 0.05

    @property
    def hard_states(self) -> torch.Tensor | None:
        """States where the network was found wrong (set by a caller such as studies.train_until, never
        checkpointed: the caller keeps them; held on the sampler's device, moved once when set): with
        :attr:`hard_fraction` > 0 each step replaces that share of its uniform points by points near
        them (:meth:`mix_hard_states`)."""
        return self._hard_states

    @hard_states.setter
    def hard_states(self, states: torch.Tensor | None) -> None:
        self._hard_states = None if states is None else states.to(self.device, torch.float32)

    @property
    def refuted(self) -> RefutedPoints | None:
        """Every point ``(x, t)`` from which the network's own policy was seen to fail, with the
        refuted-claims term's sign, margin and weight (set by a caller such as studies.train_until,
        never checkpointed; held on the sampler's device, moved once when set): each step draws
        ``hard_fraction`` of its point count of them (:meth:`refuted_batch`)."""
        return self._refuted

    @refuted.setter
    def refuted(self, points: RefutedPoints | None) -> None:
        if points is not None:
            points = points._replace(x=points.x.to(self.device), t=points.t.to(self.device))
        self._refuted = points

    def uniform(self, n: int, tmax: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` states uniform on the training box (:func:`training_box`) and times uniform on
        ``[0, tmax]``, from the run's generator (states first: resumed runs replay the same stream)."""
        g = self.generator
        x = self._low + torch.rand((n, self.network.system.state_dim), generator=g, device=self.device) * self._span
        return x, torch.rand(n, generator=g, device=self.device) * tmax

    def points(self, tmax: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """One step's ``config.points`` states and times (this process's share of them), and the vanilla
        parameterisation's boundary mask (its first ``boundary_fraction`` of points, at ``t = 0``;
        ``None`` otherwise): :meth:`points_from` this step's :meth:`draws`, then :meth:`mix_hard_states`."""
        x, t, mask = self.points_from(self.draws(), tmax)
        return self.mix_hard_states(x, mask), t, mask

    def mix_hard_states(self, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """``x`` with ``hard_fraction`` of its points (the first after the vanilla boundary's; a
        zero-level share at the end may be overlapped) moved near :attr:`hard_states`, drawn from the
        run's generator after the step's other draws (a resumed run replays them); ``x`` itself
        without hard states."""
        hard = self.hard_states
        count = int(self.hard_fraction * x.shape[0])
        if hard is None or hard.shape[0] == 0 or count == 0:
            return x
        g = self.generator
        start = 0 if mask is None else int(mask.sum())
        count = min(count, x.shape[0] - start)
        pick = torch.randint(hard.shape[0], (count,), generator=g, device=self.device)
        offset = (torch.rand((count, x.shape[1]), generator=g, device=self.device) * 2 - 1) * self.hard_radius
        near = hard.to(x.dtype)[pick] + offset * self._span
        x = x.clone()
        x[start : start + count] = torch.minimum(torch.maximum(near, self._low), self._low + self._span)
        return x

    def refuted_batch(self, tmax: float) -> RefutedPoints | None:
        """This step's refuted points: ``hard_fraction`` of the step's point count drawn (with
        replacement, from the run's generator after the step's other draws) among :attr:`refuted`'s
        points at times the curriculum has reached (``t <= tmax``); ``None`` without any."""
        every = self.refuted
        count = int(self.hard_fraction * (self.config.points // self.world_size))
        if every is None or count == 0:
            return None
        reached = torch.nonzero(every.t <= tmax).squeeze(-1)
        if reached.numel() == 0:
            return None
        pick = reached[torch.randint(reached.numel(), (count,), generator=self.generator, device=self.device)]
        return every._replace(x=every.x[pick], t=every.t[pick])

    def draw_shapes(self) -> list[tuple[int, ...]]:
        """The shapes of one step's uniform draws on [0, 1), in the stream's order: the states and the
        times, then (with ``zero_level_fraction``) the zero-level candidates' states and times."""
        c, d = self.config, self.network.system.state_dim
        n = c.points // self.world_size
        shapes: list[tuple[int, ...]] = [(n, d), (n,)]
        near = int(c.zero_level_fraction * n)
        if near:
            m = near * c.zero_level_candidates
            shapes += [(m, d), (m,)]
        return shapes

    def draws(self, out: list[torch.Tensor] | None = None) -> list[torch.Tensor]:
        """One step's uniform draws (:meth:`draw_shapes`) from the run's generator, written into ``out``
        when given: a CUDA graph's static buffers (:mod:`training.cuda_graph`), filled outside the graph
        so that the run's own generator, whose state checkpoints carry, draws every point."""
        g = self.generator
        if out is None:
            return [torch.rand(shape, generator=g, device=self.device) for shape in self.draw_shapes()]
        for buffer in out:
            torch.rand(buffer.shape, generator=g, out=buffer)
        return out

    def points_from(
        self, draws: list[torch.Tensor], tmax: float | torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The step's points from its :meth:`draws` (``tmax`` a float, or a 0-d tensor in a CUDA graph):
        uniform on the training box and on ``[0, tmax]``, the last ``zero_level_fraction`` of them
        replaced by the candidates nearest the network's zero level. Reads nothing back from the device."""
        c = self.config
        x, t = self._low + draws[0] * self._span, draws[1] * tmax
        n = t.shape[0]
        mask = None
        if c.parameterisation in LEARNED_BOUNDARY:
            mask = torch.zeros(n, dtype=torch.bool, device=self.device)
            mask[: int(c.boundary_fraction * n)] = True
            t = torch.where(mask, torch.zeros_like(t), t)
        if len(draws) > 2:  # the last points (never the vanilla boundary's first ones)
            near = int(c.zero_level_fraction * n)
            x[n - near :], t[n - near :] = self._nearest_zero_level(
                self._low + draws[2] * self._span, draws[3] * tmax, near
            )
        return x, t, mask

    def near_zero_level(self, count: int, tmax: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` states and times with the smallest ``|V|`` among ``zero_level_candidates x count``
        uniform draws (one forward pass without gradients)."""
        return self._nearest_zero_level(*self.uniform(count * self.config.zero_level_candidates, tmax), count)

    def _nearest_zero_level(self, x: torch.Tensor, t: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            keep = self.network(x, t).abs().topk(count, largest=False).indices
        return x[keep], t[keep]

    def lower_bound_labels(self, tmax: float) -> Labels:
        """Fresh states and times labelled with what the network's policy achieves (``J <= V``), by the
        ``config.lower_bound`` rule (``"mpc"`` or ``"policy"``); this process's share of ``lower_bound_points``."""
        c = self.config
        x, t = self.uniform(c.lower_bound_points // self.world_size, tmax)
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

    def resume_stream(self, state: torch.Tensor | None, trained_on: str, step: int) -> bool:
        """Continue a checkpoint's stream: its generator ``state`` if it was drawn on this kind of device
        (``trained_on``), else (or with no ``state``: the checkpoint holds no stream of this process)
        reseed from :func:`moved_run_seed` of this process's seed at ``step``. Returns whether the
        stream was reseeded (the caller says so: the points differ from an uninterrupted run's)."""
        if state is not None and trained_on == self.device.type:
            self.generator.set_state(state)
            return False
        self.generator.manual_seed(moved_run_seed(self.seed, step))
        return True
