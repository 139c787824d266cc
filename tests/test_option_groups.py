"""The frozen option groups that keep long parameter lists short refuse bad values when made, naming
them, and their defaults are the behaviour the functions had before (RecordingSettings, LossSettings,
SourceLoading, DemoSettings, RecordedEpisodes)."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from reach_envs.recording import RecordingSettings
from studies.batch_verification import SourceLoading
from studies.demo import DemoSettings, run_demo
from studies.filter_study import RecordedEpisodes
from training.loss import LossSettings, LossWeights


@pytest.mark.parametrize(
    ("make", "named"),
    [
        (lambda: RecordingSettings(every=0), "every"),
        (lambda: RecordingSettings(every=1.5), "1.5"),
        (lambda: RecordingSettings(max_steps=-1), "max_steps"),
        (lambda: LossSettings(gradient_bound=-1.0), "gradient_bound"),
        (lambda: LossSettings(gradient_bound=float("nan")), "gradient_bound"),
        (lambda: LossSettings(residual_fn="autograd"), "'autograd'"),
        (lambda: LossSettings(weights={"gradient": 2.0}), "weights"),
        (lambda: SourceLoading(format="onnx"), "'onnx'"),
        (lambda: SourceLoading(system=3), "3"),
        (lambda: SourceLoading(layout=5), "5"),
        (lambda: DemoSettings(grid=3), "grid"),
        (lambda: DemoSettings(samples=0), "samples"),
        (lambda: DemoSettings(episodes=0), "episodes"),
        (lambda: DemoSettings(budget_s=0.0), "budget_s"),
        (lambda: DemoSettings(seed=-1), "seed"),
        (lambda: DemoSettings(compile="auto"), "'auto'"),
        (lambda: RecordedEpisodes(seeds=()), "at least one seed"),
        (lambda: RecordedEpisodes(seeds=(0, -2)), "seed"),
        (lambda: RecordedEpisodes(seeds=(0, 1), initial_states=np.zeros((1, 3))), "1 starts for 2 seeds"),
    ],
)
def test_option_groups_refuse_bad_values_when_made(make, named):
    with pytest.raises(ValueError, match=re.escape(named)):
        make()


def test_option_groups_are_frozen_with_the_former_defaults():
    assert (RecordingSettings().max_steps, RecordingSettings().every) == (None, 1)
    assert RecordingSettings(max_steps=3.0, every=2.0) == RecordingSettings(3, 2)  # whole floats become ints
    loss = LossSettings()
    assert (loss.residual_fn, loss.gradient_bound, loss.weights) == (None, None, LossWeights())
    assert SourceLoading() == SourceLoading(system=None, format="auto", layout=None)
    assert RecordedEpisodes().seeds == (0, 1, 2) and RecordedEpisodes().initial_states is None
    demo = DemoSettings()
    assert (demo.budget_s, demo.grid, demo.samples, demo.episodes, demo.seed, demo.compile) == (
        180.0,
        101,
        10_000,
        500,
        0,
        None,
    )
    for settings in (RecordingSettings(), loss, SourceLoading(), demo, RecordedEpisodes()):
        with pytest.raises(dataclasses.FrozenInstanceError):
            settings.seed = 1


def test_run_demo_refuses_an_unknown_keyword_before_any_work(tmp_path):
    with pytest.raises(ValueError, match=r"unknown demo setting\(s\) \['gird'\]"):
        run_demo(tmp_path / "demo", gird=21)
    assert not (tmp_path / "demo").exists()
