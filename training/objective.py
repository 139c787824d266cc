"""The loss a run trains on, with what its terms need built up front so that a bad configuration fails at once.

Built with the run, before any step: the HJI residual function (compiled or not), the gradient
bound in the network's coordinates, the pairwise union that bounds ``V`` from above (loaded and
checked), and the check that the system suits the lower-bound labels (which :mod:`training.sampling`
draws).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from reach.systems import ControlAffineSystem, MultiVehicle
from training import pretrained
from training.config import TrainConfig
from training.loss import Anchors, LossSettings, LossWeights, RefutedPoints, loss_terms, residual_function
from training.network import ValueNetwork
from training.policy_lower_bounds import check_lower_bound_system
from training.sampling import Labels


def load_upper_bound(config: TrainConfig, system: ControlAffineSystem) -> Any:
    """The union of pairwise BRTs that ``config.upper_bound`` names (a pair grid ``.npz``, or the shipped
    compact one, ``"pretrained:relativepair"``), loaded (and refused) before training."""
    if config.upper_bound is None:
        return None
    from groundtruth.pairwise import PairwiseUnion  # lazy: the grid solver loads only for runs that use it

    if not isinstance(system, MultiVehicle):
        raise ValueError(f"upper_bound: a pairwise union bounds multi-vehicle systems only, not {system.name}")
    path = config.upper_bound
    if pretrained.is_pretrained(path):
        path = pretrained.checkpoint_path(path)  # checked against its card's digest
    elif not Path(path).is_file():
        raise ValueError(f"upper_bound: no such file {config.upper_bound!r}")
    union = PairwiseUnion.load(system, path)
    if union.system.horizon < system.horizon:
        raise ValueError(
            f"upper_bound {config.upper_bound}: its pair solution reaches t = {union.system.horizon:g}, "
            f"the system's horizon is {system.horizon:g}"
        )
    return union


class Objective(torch.nn.Module):
    """The training loss of ``network`` under ``config``, at whatever points a step draws.

    A module holding the network, so that DistributedDataParallel can wrap the whole loss
    (:mod:`training.distributed`): a step calls it once, and the backward pass that follows averages
    the network's gradients over the processes."""

    def __init__(self, config: TrainConfig, network: ValueNetwork) -> None:
        super().__init__()
        self.config = config
        self.network = network
        #: the residual function, the gradient bound in the network's normalised coordinates
        #: (``gradient_bound`` x l's steepest slope) and the terms' weights, fixed for the run
        self.settings = LossSettings(
            residual_fn=residual_function(network, config.gradients, config.compile_resolved()),
            gradient_bound=None if config.gradient_bound is None else config.gradient_bound * network.margin_slope(),
            weights=LossWeights(
                norm=config.loss,
                boundary=config.boundary_weight,
                gradient=config.gradient_weight,
                upper_bound=config.upper_bound_weight,
                lower_bound=config.lower_bound_weight,
            ),
        )
        self.upper_bound = load_upper_bound(config, network.system)
        #: whether the union checks its points (finite, within its horizon) before interpolating. A
        #: step captured as a CUDA graph turns this off, since the checks read back from the device;
        #: its points are the sampler's own, drawn inside the domain and the time range.
        self.check_points = True
        if config.lower_bound is not None:
            check_lower_bound_system(network.system)

    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        mask: torch.Tensor | None,
        pde: bool,
        labels: Labels | None,
        refuted: RefutedPoints | None = None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The loss and its terms (detached 0-d tensors, read back by the caller) at states ``x`` and
        times ``t`` (``mask``: the vanilla boundary points; ``pde``: whether the residual counts yet;
        ``labels``: the lower-bound term's points, if any; ``refuted``: the refuted-claims term's)."""
        return loss_terms(
            self.network,
            x,
            t,
            pde=pde,
            boundary_mask=mask,
            anchors=Anchors(None if self.upper_bound is None else self.upper_bound_at(x, t), labels, refuted),
            settings=self.settings,
        )

    def upper_bound_at(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The union's value at the sampled points (``+inf`` where no pair grid covers them)."""
        with torch.no_grad():  # the pair grids interpolate on the points' own device
            union = self.upper_bound.value_where_known(x.detach(), t.detach(), checked=self.check_points)
            return union.to(x.dtype)
