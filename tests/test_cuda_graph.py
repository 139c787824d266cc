"""The training step as one CUDA graph (training.cuda_graph): the same training as the eager step.

On the CPU the graph's body runs eagerly on the graph's buffers (``capture=False``): that checks the
plumbing (draws written into fixed buffers from the run's generator, the time range and labels as
device values, the checkpoint's portable optimizer state) bit for bit against the eager trainer. On a
CUDA machine the last test captures and replays the real graph.
"""

from __future__ import annotations

import pytest
import torch

from training.config import TrainConfig
from training.cuda_graph import GraphedStep, make_capturable, portable_state
from training.trainer import Trainer

TINY = {"width": 16, "points": 256, "log_every": 5, "checkpoint_every_s": 0.0}


def _trained(tmp_path, name: str, graphed: bool, steps: int = 6, **options: object) -> tuple[Trainer, list]:
    trainer = Trainer(TrainConfig(steps=steps, seed=3, **TINY, **options), tmp_path / name, progress=False)
    if graphed:
        trainer.graphed = GraphedStep(trainer.sampler, trainer.objective, trainer.optimizer, capture=False)
    losses = [trainer._optimise().terms for _ in range(steps)]
    return trainer, losses


@pytest.mark.parametrize(
    "options",
    [
        {"system": "air3d", "zero_level_fraction": 0.25},
        {"system": "multivehicle9d", "lower_bound": "policy", "lower_bound_points": 16, "lower_bound_every": 2},
        {"system": "multivehicle9d", "upper_bound": "PAIR"},
    ],
    ids=["air3d-zero-level", "9d-lower-bound", "9d-upper-bound"],
)
def test_graph_body_trains_exactly_as_the_eager_step(tmp_path, options, request):
    """Six steps through the graph's buffers give the eager trainer's loss terms and weights exactly:
    the same points from the same generator, the same labels, the same update. With the pair union's
    cap, the graph's unchecked interpolation (no read-backs) gives the checked one's values."""
    if options.get("upper_bound") == "PAIR":
        path = request.getfixturevalue("pair_grid").save(tmp_path / "pair.npz")
        options = {**options, "upper_bound": str(path)}
    eager, eager_terms = _trained(tmp_path, "eager", False, **options)
    graphed, graphed_terms = _trained(tmp_path, "graphed", True, **options)
    assert graphed_terms == eager_terms
    for a, b in zip(eager.network.parameters(), graphed.network.parameters()):
        assert torch.equal(a, b)
    assert torch.equal(eager.generator.get_state(), graphed.generator.get_state())


def test_portable_state_loads_into_a_plain_adam_and_matches_it():
    """A capturable optimizer's state (lr a device scalar, step counts on the device) saves as a
    plain Adam's: lr a float, capturable off, step counts float32 on the CPU."""
    torch.manual_seed(0)
    weights = torch.nn.Parameter(torch.randn(4))
    plain = torch.optim.Adam([weights], lr=3e-3)
    (weights**2).sum().backward()
    plain.step()
    expected = plain.state_dict()
    make_capturable(plain, torch.device("cpu"))  # the form a graphed run holds (moved to the CPU here)
    assert plain.param_groups[0]["capturable"] and isinstance(plain.param_groups[0]["lr"], torch.Tensor)
    state = portable_state(plain.state_dict())
    group = state["param_groups"][0]
    assert group["lr"] == pytest.approx(3e-3) and not isinstance(group["lr"], torch.Tensor)
    assert group["capturable"] is False
    step = state["state"][0]["step"]
    assert step.device.type == "cpu" and step.dtype == torch.float32 and float(step) == 1.0
    fresh = torch.optim.Adam([torch.nn.Parameter(weights.detach().clone())], lr=1.0)
    fresh.load_state_dict(state)
    assert torch.equal(fresh.state_dict()["state"][0]["exp_avg"], expected["state"][0]["exp_avg"])


@pytest.mark.parametrize(
    ("options", "named"),
    [
        ({"device": "cuda", "parameterisation": "vanilla"}, "vanilla parameterisation"),
        ({"device": "cuda", "gradients": "autograd"}, "autograd"),
        ({"device": "cpu"}, "need a CUDA device"),
    ],
)
def test_runs_that_cannot_replay_a_graph_say_why(options, named):
    """The reason names the run's setting (checked without a GPU: the device check comes first in
    ``validate`` there), and requiring a graph on the CPU fails validation with it."""
    config = TrainConfig(steps=1, cuda_graph=True, **options)
    assert named in config.cuda_graph_unsupported()
    assert TrainConfig(steps=1, device="cuda").cuda_graph_unsupported() is None
    if options["device"] == "cpu":
        with pytest.raises(ValueError, match=named):
            config.validate()


def test_unset_cuda_graph_trains_eagerly_on_the_cpu(tmp_path):
    trainer, _ = _trained(tmp_path, "run", False, steps=2)
    assert not trainer.uses_cuda_graph() and trainer.graphed is None
    with pytest.raises(ValueError, match="true, false or null"):
        TrainConfig(steps=1, cuda_graph="yes").validate()
    with pytest.raises(ValueError, match="CUDA GPU's mode"):
        TrainConfig(steps=1, matmul_precision="tf32").validate()
    with pytest.raises(ValueError, match="'float32' or 'tf32'"):
        TrainConfig(steps=1, matmul_precision="bfloat16").validate()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_captured_step_follows_the_eager_loss_curve_on_cuda(tmp_path):
    """On a GPU: the warm-up, the capture and the replays train like the eager step (float tolerance:
    capturable Adam computes its bias corrections on the device), and a checkpoint of the graphed
    run resumes eagerly."""
    options = {"device": "cuda", "steps": 12, "system": "air3d", "zero_level_fraction": 0.25}
    eager = Trainer(TrainConfig(seed=3, cuda_graph=False, **TINY, **options), tmp_path / "eager", progress=False)
    graphed = Trainer(TrainConfig(seed=3, **TINY, **options), tmp_path / "graphed", progress=False)
    a = [eager._optimise().terms["loss"] for _ in range(12)]
    b = [graphed._optimise().terms["loss"] for _ in range(12)]
    assert graphed.graphed is not None and graphed.graphed.captured and eager.graphed is None
    assert b == pytest.approx(a, rel=1e-4)
    graphed.run.write_config(graphed.config)  # what train() writes first
    graphed._save()
    resumed = Trainer.resume(tmp_path / "graphed", progress=False, cuda_graph=False, steps=14)
    resumed._optimise()
    assert resumed.step == 13 and resumed.graphed is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_tf32_training_sets_and_restores_torchs_matmul_mode(tmp_path):
    from training.trainer import matmul_precision

    before = torch.backends.cuda.matmul.allow_tf32
    with matmul_precision("tf32"):
        assert torch.backends.cuda.matmul.allow_tf32
    assert torch.backends.cuda.matmul.allow_tf32 == before
    config = TrainConfig(device="cuda", steps=5, matmul_precision="tf32", **TINY)
    summary = Trainer(config, tmp_path / "run", progress=False).train()
    assert summary["steps"] == 5 and torch.backends.cuda.matmul.allow_tf32 == before
