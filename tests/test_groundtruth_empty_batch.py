"""A grid solution answers an empty batch of states with an empty batch (a culled fleet has no pair)."""

import torch

from groundtruth.solution import GridSolution
from training import pretrained


def test_an_empty_batch_interpolates_to_an_empty_batch():
    sol = GridSolution.load(pretrained.checkpoint_path("pretrained:relativepair"), outside="clamp")
    none = torch.zeros(0, 3, dtype=torch.float64)
    value, grad = sol.value_and_gradient(none, 1.0)
    assert value.shape == (0,) and grad.shape == (0, 3)
    assert sol.value(none, 1.0).shape == (0,)
    assert sol.gradient(none.reshape(0, 0, 3), 1.0).shape == (0, 0, 3)
