"""One training step replayed as a single CUDA graph, so that a GPU step costs its arithmetic, not its launches.

Why: eager, the 9D default step launches hundreds of small kernels (the sine layers'
value and input derivatives, their backward pass, Adam's update), and on a GPU it ran at the same
rate whether it took 8,192 points or 65,536: the GPU waited on the CPU to launch (measured:
docs/results/benchmarks.md, *On a GPU*). A captured step is one launch.

What the graph holds: the step's points made from its uniform draws (:meth:`PointSampler.points_from`,
the zero-level selection included), the loss (:class:`training.objective.Objective`), the backward
pass and Adam's update (``capturable``, with its learning rate a device scalar).

What stays outside it, each step, in this order:

* the draws themselves, written into the graph's buffers from the run's own generator
  (:meth:`PointSampler.draws`): checkpoints carry that generator's state, so a graphed run draws
  the same points as an eager one and resumes its stream in either mode;
* the schedule's learning rate and time range, written into device scalars;
* a refresh of the lower-bound labels when one is due (rollouts, copied into fixed buffers);
* reading the loss terms back, all in one transfer: the divergence check and the log need them.

The first :data:`WARMUP_STEPS` steps run eagerly on a side stream (the compiled residual compiles,
the allocator settles), as CUDA graph capture requires; the step after them is captured and every
later step replays it. Runs that cannot be captured (:meth:`TrainConfig.cuda_graph_unsupported`,
and distributed runs: DistributedDataParallel's gradient all-reduce is not captured) train eagerly.

One difference from the eager step: the eager step checks the loss before Adam's update, a replayed
graph updates first. A diverged run's checkpoint is the last good one either way (nothing is saved
after a non-finite loss); only the network in memory differs.
"""

from __future__ import annotations

import torch

from training.loss import terms_to_floats
from training.objective import Objective
from training.sampling import Labels, PointSampler

#: eager steps on a side stream before the capture (compilation, allocator warm-up)
WARMUP_STEPS = 3


def make_capturable(optimizer: torch.optim.Optimizer, device: torch.device) -> None:
    """Turn an Adam optimizer into its capturable form: its learning rate a scalar on ``device`` (the
    schedule writes into it before each replay) and each parameter's step count on the device."""
    for group in optimizer.param_groups:
        group["capturable"] = True
        if not isinstance(group["lr"], torch.Tensor):
            group["lr"] = torch.tensor(float(group["lr"]), device=device)
        for p in group["params"]:
            state = optimizer.state.get(p)
            if state and "step" in state:
                state["step"] = state["step"].to(device=device, dtype=torch.float32)


def portable_state(state: dict) -> dict:
    """An optimizer ``state_dict`` that loads into a plain (eager, any device) Adam: a capturable
    optimizer's learning rate back to a float, ``capturable`` off and its step counts on the CPU, as
    an eager run writes them. Checkpoints store this form, so a run resumes in either mode."""
    groups = []
    for group in state["param_groups"]:
        group = dict(group)
        if isinstance(group.get("lr"), torch.Tensor):
            group["lr"] = float(group["lr"])
        if group.get("capturable"):
            group["capturable"] = False
        groups.append(group)
    per_param = {}
    for key, values in state["state"].items():
        values = dict(values)
        if isinstance(values.get("step"), torch.Tensor):
            values["step"] = values["step"].detach().to("cpu", torch.float32)
        per_param[key] = values
    return {"state": per_param, "param_groups": groups}


class GraphedStep:
    """A run's step as a CUDA graph, over the run's ``sampler``, ``objective`` and (Adam) ``optimizer``:
    call it with the schedule's learning rate and time range and the current lower-bound labels; it
    returns the step's loss terms as floats.

    ``capture=False`` runs the same body eagerly every step, on buffers filled the same way: the CPU
    tests check that this plumbing trains exactly as the eager trainer does."""

    def __init__(
        self, sampler: PointSampler, objective: Objective, optimizer: torch.optim.Optimizer, capture: bool = True
    ) -> None:
        self.sampler, self.objective, self.optimizer = sampler, objective, optimizer
        self.capture = capture
        objective.check_points = False  # no read-backs in the graph: the points are the sampler's own
        device = sampler.device
        if capture:
            make_capturable(optimizer, device)
        self._draws = [torch.empty(shape, device=device) for shape in sampler.draw_shapes()]
        self._tmax = torch.zeros((), device=device)
        self._labels: Labels | None = None  # fixed buffers the graph reads
        self._labels_from: Labels | None = None  # the trainer's labels they were copied from
        self._graph: torch.cuda.CUDAGraph | None = None
        self._terms: dict[str, torch.Tensor] | None = None  # the captured step's outputs
        self._eager_steps = 0
        self._stream = torch.cuda.Stream(device) if capture else None

    @property
    def captured(self) -> bool:
        """Whether the step has been captured (every step from here on is one replay)."""
        return self._graph is not None

    def __call__(self, lr: float, tmax: float, labels: Labels | None) -> dict[str, float]:
        self.sampler.draws(self._draws)
        self._tmax.fill_(tmax)
        self._take_labels(labels)
        for group in self.optimizer.param_groups:
            if isinstance(group["lr"], torch.Tensor):
                group["lr"].fill_(lr)
            else:
                group["lr"] = lr
        if self._graph is not None:
            self._graph.replay()
        elif not self.capture:
            self._terms = self._eager()
        elif self._eager_steps < WARMUP_STEPS:
            self._eager_steps += 1
            self._stream.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(self._stream):
                self._terms = self._eager()
            torch.cuda.current_stream().wait_stream(self._stream)
        else:
            self.optimizer.zero_grad(set_to_none=True)  # the graph's backward assigns its gradients
            self._graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self._graph):
                self._terms = self._body()
            self._graph.replay()  # capturing ran nothing: this is the step
        return terms_to_floats(self._terms)

    def _take_labels(self, labels: Labels | None) -> None:
        """Copy freshly refreshed labels into the buffers the graph reads (the same tensors every step)."""
        if labels is None or labels is self._labels_from:
            return
        if self._labels is None:
            self._labels = tuple(torch.empty_like(v) for v in labels)
        for buffer, value in zip(self._labels, labels):
            buffer.copy_(value)
        self._labels_from = labels

    def _eager(self) -> dict[str, torch.Tensor]:
        self.optimizer.zero_grad(set_to_none=True)
        return self._body()

    def _body(self) -> dict[str, torch.Tensor]:
        """The captured work: points from the draws, the loss, its backward pass and Adam's update."""
        x, t, mask = self.sampler.points_from(self._draws, self._tmax)
        loss, terms = self.objective(x, t, mask, True, self._labels)
        loss.backward()
        self.optimizer.step()
        return terms
