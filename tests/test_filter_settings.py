"""FilterSettings: one frozen group of filter options, checked once and passed whole to every layer."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import gymnasium as gym
import pytest
import torch

import reach_envs  # noqa: F401  (registers the environments)
from reach.systems import Air3D, MultiVehicle9D
from reach_cli import main
from safety import FilterSettings, SafetyFilter, SafetyFilterWrapper
from safety.filters.settings import DEFAULT_GAMMA, FIELDS, default_threshold, make_filter_settings
from safety.filters.wrappers import SafetyFilterParallelWrapper, SafetyFilterVectorWrapper
from studies.filter_configs import EpisodeSettings, FilterConfig, FilterGrid, FilterStudySettings, StudyOutput
from training import NeuralValueFunction, ValueNetwork


def _network(system, seed=0):
    torch.manual_seed(seed)
    return NeuralValueFunction(ValueNetwork(system, "ssssl", width=16))


# ---------------------------------------------------------------------------- checked once, naming the value
@pytest.mark.parametrize(
    ("field", "bad"),
    [
        ("kind", "smoooth"),
        ("kind", None),
        ("threshold", float("nan")),
        ("threshold", float("inf")),
        ("threshold", True),
        ("threshold", "0.1"),
        ("time_to_go", -1.0),
        ("time_to_go", "later"),
        ("time_to_go", float("nan")),
        ("gamma", -0.5),
        ("gamma", float("inf")),
        ("backup_horizon", -2.0),
        ("backup_horizon", float("nan")),
        ("backup_disturbance", "optimistic"),
        ("policy", "greedyy"),
    ],
)
def test_a_bad_setting_is_refused_naming_the_field_and_the_value(field, bad):
    with pytest.raises(ValueError) as err:
        FilterSettings(**{field: bad})
    message = str(err.value)
    assert repr(bad) in message, message
    assert (field if field != "kind" else "filter kind") in message, message


def test_good_settings_are_accepted_and_frozen():
    s = FilterSettings(kind="lookahead", threshold=0.0, time_to_go="remaining", gamma=0, backup_horizon=0)
    assert FilterSettings(time_to_go=0.5).time_to_go == 0.5
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.kind = "switch"  # type: ignore[misc]
    assert FilterSettings() == FilterSettings(**FilterSettings().keywords())  # keywords rebuild it


def test_every_default_comes_from_the_dataclass():
    s = FilterSettings()
    assert (s.kind, s.threshold, s.time_to_go, s.backup_horizon, s.backup_disturbance, s.policy) == (
        "switch",
        None,
        None,
        None,
        "robust",
        None,
    )
    assert DEFAULT_GAMMA == s.gamma == 5.0
    assert FilterGrid().kinds == (s.kind,) and FilterGrid().gammas == (s.gamma,) and FilterGrid().shared == s
    assert FilterConfig("nominal").settings == s
    assert s.backup_policy == "greedy" and FilterSettings(kind="lookahead").backup_policy == "gradient"


def test_the_threshold_rule_lives_in_one_place():
    system = Air3D()
    assert FilterSettings().threshold_for(system) == 0.0  # a bare filter: no control period
    assert FilterSettings().threshold_for(system, 0.02) == pytest.approx(default_threshold(system, 0.02)) == 0.06
    assert FilterSettings(kind="lookahead").threshold_for(system, 0.02) == 0.0
    assert FilterSettings(threshold=0.3).threshold_for(system, 0.02) == 0.3


# ---------------------------------------------------------------------------- keywords -> settings, one place
def test_make_filter_settings_builds_or_replaces_and_refuses_unknown_names():
    base = FilterSettings(kind="smooth", gamma=2.0, threshold=0.1)
    assert make_filter_settings() == FilterSettings()
    assert make_filter_settings(None, kind="lookahead") == FilterSettings(kind="lookahead")
    assert make_filter_settings(base) is base
    assert make_filter_settings(base, threshold=None, time_to_go=None) is base  # None: not given
    assert make_filter_settings(base, gamma=3.0) == dataclasses.replace(base, gamma=3.0)
    with pytest.raises(TypeError, match="'gamm'"):
        make_filter_settings(None, gamm=1.0)
    with pytest.raises(TypeError, match="FilterSettings"):
        make_filter_settings({"kind": "switch"})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'bogus'"):
        make_filter_settings(base, kind="bogus")
    assert set(FIELDS) == {f.name for f in dataclasses.fields(FilterSettings)}


@pytest.mark.parametrize(
    ("keywords", "settings", "extra"),
    [
        ({"threshold": 0.1}, FilterSettings(threshold=0.1), {}),
        ({"kind": "smooth", "gamma": 2.0}, FilterSettings(kind="smooth", gamma=2.0), {}),
        (
            {"threshold": 0.0, "kind": "lookahead", "backup_horizon": 0.1, "backup_disturbance": "model"},
            FilterSettings(kind="lookahead", threshold=0.0, backup_horizon=0.1, backup_disturbance="model"),
            {"dt": 0.02},
        ),
        ({"policy": "gradient"}, FilterSettings(policy="gradient"), {}),
    ],
)
def test_keywords_and_settings_give_the_same_filter(keywords, settings, extra):
    vf = _network(Air3D())
    by_keywords = SafetyFilter(vf, **keywords, **extra)
    by_settings = SafetyFilter(vf, settings=settings, **extra)
    assert by_keywords.settings == by_settings.settings
    for name in ("threshold", "kind", "gamma", "backup_horizon", "backup_steps", "backup_disturbance", "policy_name"):
        assert getattr(by_keywords, name) == getattr(by_settings, name), name
    x = Air3D().sample_states(64, generator=torch.Generator().manual_seed(0))
    nominal = torch.linspace(-3, 3, 64).unsqueeze(-1)
    u1, i1 = by_keywords(x, 1.0, nominal)
    u2, i2 = by_settings(x, 1.0, nominal)
    assert torch.equal(u1, u2) and torch.equal(i1.intervened, i2.intervened)


def test_a_keyword_beside_settings_replaces_that_field_only():
    f = SafetyFilter(_network(Air3D()), 0.2, settings=FilterSettings(kind="smooth", gamma=1.0), gamma=3.0)
    assert (f.kind, f.threshold, f.gamma) == ("smooth", 0.2, 3.0)
    f.threshold = 0.4  # the threshold may change between calls; settings read it back
    assert f.settings == FilterSettings(kind="smooth", threshold=0.4, gamma=3.0)


# ---------------------------------------------------------------------------- passed whole, every adapter
def test_the_same_settings_object_reaches_every_adapter_and_its_filter():
    from reach_envs.parallel import parallel_env

    settings = FilterSettings(kind="lookahead", backup_horizon=0.1, backup_disturbance="model", policy="gradient")
    env = SafetyFilterWrapper(gym.make("Air3D-v0"), _network(Air3D()), settings=settings)
    venv = SafetyFilterVectorWrapper(
        gym.make_vec("Air3D-v0", num_envs=2, vectorization_mode="vector_entry_point"),
        _network(Air3D()),
        settings=settings,
    )
    penv = SafetyFilterParallelWrapper(parallel_env("three-car-9d"), _network(MultiVehicle9D()), settings=settings)
    for wrapper in (env, venv, penv):
        assert wrapper.filter_settings is settings
        f = wrapper.safety_filter
        assert f.settings == dataclasses.replace(settings, threshold=0.0)  # the lookahead's rule resolved
        assert (f.backup_horizon, f.backup_steps, f.backup_disturbance, f.policy_name) == (0.1, 5, "model", "gradient")


def test_the_gymnasium_spec_records_the_settings_and_rebuilds_them():
    settings = FilterSettings(kind="smooth", gamma=2.0, time_to_go=0.8, threshold=0.05)
    env = SafetyFilterWrapper(gym.make("Air3D-v0"), _network(Air3D()), settings=settings)
    recorded = env.spec.additional_wrappers[-1].kwargs
    assert {k: recorded[k] for k in FIELDS} == settings.keywords()
    rebuilt = gym.make(env.spec)
    assert isinstance(rebuilt, SafetyFilterWrapper) and rebuilt.filter_settings == settings
    assert rebuilt.safety_filter.threshold == 0.05 and rebuilt.safety_filter.gamma == 2.0
    by_keywords = SafetyFilterWrapper(gym.make("Air3D-v0"), _network(Air3D()), 0.05, 0.8, kind="smooth", gamma=2.0)
    assert by_keywords.filter_settings == settings
    assert {k: by_keywords.spec.additional_wrappers[-1].kwargs[k] for k in FIELDS} == settings.keywords()


def test_a_bad_time_to_go_is_refused_by_the_settings_before_the_env_is_touched():
    with pytest.raises(ValueError, match=r"time_to_go .*-1"):
        SafetyFilterWrapper(gym.make("Air3D-v0"), _network(Air3D()), time_to_go=-1)


def test_filter_config_holds_the_settings_whole():
    vf = _network(Air3D())
    settings = FilterSettings(kind="smooth", gamma=1.5, threshold=0.2)
    config = FilterConfig("net", vf, settings=settings)
    assert config.settings is settings and (config.kind, config.gamma, config.threshold) == ("smooth", 1.5, 0.2)
    assert FilterConfig("net", vf, 0.2, kind="smooth", gamma=1.5) == config  # keywords: the same configuration
    with pytest.raises(AttributeError):
        _ = config.nothing


def test_evaluate_filters_passes_each_configuration_s_settings_whole(monkeypatch):
    import studies.filter_episodes as episodes

    seen = []

    class Spy(SafetyFilterVectorWrapper):
        def __init__(self, env, value_function=None, *args, settings=None, **kwargs):
            seen.append(settings)
            super().__init__(env, value_function, *args, settings=settings, **kwargs)

    monkeypatch.setattr(episodes, "SafetyFilterVectorWrapper", Spy)
    settings = FilterSettings(kind="smooth", gamma=1.0, threshold=0.1, policy="gradient")
    config = FilterConfig("net", _network(Air3D()), settings=settings)
    (row,) = episodes.evaluate_filters("air3d", [config], episodes=2, seed=0)
    assert seen == [settings] and seen[0] is settings  # no time_to_go given: the very object
    assert (row["kind"], row["gamma"], row["threshold"], row["policy"]) == ("smooth", 1.0, 0.1, "gradient")
    episodes.evaluate_filters("air3d", [config], episodes=2, seed=0, time_to_go=0.9)
    assert seen[-1] == dataclasses.replace(settings, time_to_go=0.9)


# ---------------------------------------------------------------------------- the study and the CLI
def test_the_study_settings_route_flat_keywords_and_refuse_what_they_do_not_know():
    s = FilterStudySettings.from_options(
        episodes=7, kinds=["switch", "smooth"], gammas=[1.0, 2.0], gif="x.gif", backup_horizon=0.3, time_to_go=0.5
    )
    assert s.episodes == EpisodeSettings(episodes=7)
    assert s.filters.kinds == ("switch", "smooth") and s.filters.gammas == (1.0, 2.0)
    assert s.filters.shared == FilterSettings(backup_horizon=0.3, time_to_go=0.5)
    assert s.output == StudyOutput(gif="x.gif")
    with pytest.raises(TypeError, match="threshold"):
        FilterStudySettings.from_options(threshold=0.1)  # a study's thresholds are a list
    with pytest.raises(TypeError, match="'bogus'"):
        FilterStudySettings.from_options(bogus=1)
    with pytest.raises(ValueError, match="'nowhere'"):
        FilterStudySettings.from_options(start_from="nowhere")
    with pytest.raises(ValueError, match="'smoooth'"):
        FilterGrid(kinds=("switch", "smoooth"))
    with pytest.raises(ValueError, match=r"gamma .*-1"):
        FilterGrid(kinds=("smooth",), gammas=(1.0, -1.0))


def test_the_grid_shares_its_settings_with_every_configuration():
    vf = _network(Air3D())
    shared = FilterSettings(time_to_go=0.5, policy="gradient", backup_horizon=0.2)
    grid = FilterGrid(thresholds=(None, 0.1), kinds=("switch", "smooth"), gammas=(1.0, 2.0), shared=shared)
    nominal, *configs = grid.configs([("net", vf)])
    assert nominal.value_function is None and len(configs) == 2 + 4
    for c in configs:
        assert dataclasses.replace(c.settings, kind="switch", threshold=None, gamma=shared.gamma) == shared
    assert [(c.kind, c.threshold, c.gamma) for c in configs] == [
        ("switch", None, 5.0),
        ("switch", 0.1, 5.0),
        ("smooth", None, 1.0),
        ("smooth", None, 2.0),
        ("smooth", 0.1, 1.0),
        ("smooth", 0.1, 2.0),
    ]


def test_a_table_of_other_episodes_is_refused_before_any_episode(tmp_path: Path, monkeypatch):
    import studies.filter_study as filter_study

    def no_episodes(*args, **kwargs):
        raise AssertionError("episodes ran before the table was checked")

    monkeypatch.setattr(filter_study, "evaluate_filters", no_episodes)
    out = tmp_path / "fe.csv"
    out.with_suffix(".json").write_text(json.dumps({"scene": "air3d", "episodes": 5, "seed": 0, "results": []}))
    with pytest.raises(ValueError, match=r"\(episodes: 5 there, 2 now\)"):
        filter_study.run_filter_study("air3d", [], out, episodes=2, merge=True)


def test_the_cli_builds_one_settings_object_from_its_options(monkeypatch, tmp_path: Path, capsys):
    import studies.filter_study as filter_study

    captured = {}

    def capture(scene, value_functions, out, settings=None, **options):
        captured["settings"] = settings
        raise ValueError("captured")

    monkeypatch.setattr(filter_study, "run_filter_study", capture)
    argv = ["filter-eval", "--out", str(tmp_path / "f.csv"), "--episodes", "3", "--filters", "lookahead,smooth"]
    argv += ["--backup-horizon", "0.4", "--policy", "gradient", "--time-to-go", "remaining", "--gammas", "1,2"]
    assert main(argv) == 2 and "captured" in capsys.readouterr().err
    study = captured["settings"]
    assert isinstance(study, FilterStudySettings)
    assert study.filters.shared == FilterSettings(backup_horizon=0.4, policy="gradient", time_to_go="remaining")
    assert study.filters.kinds == ("lookahead", "smooth") and study.filters.gammas == (1.0, 2.0)
    assert study.episodes.episodes == 3 and study.output.merge
    assert study.output.header["backup_disturbance"] == "robust"  # the dataclass's default, in the header
    main(["filter-eval", "--out", str(tmp_path / "g.csv")])
    assert captured["settings"].filters == FilterGrid()  # no option given: every default the dataclass's


def test_the_cli_options_default_to_the_dataclass():
    from reach_cli import build_parser
    from reach_cli import filter_eval as command

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices["filter-eval"]
    actions = {a.dest: a for a in sub._actions}
    help_text = " ".join(sub.format_help().split())
    for option, field, _, _ in command.FILTER_OPTIONS:
        assert field in FIELDS, option
        assert actions[field].default is None, f"{option} carries its own default"
        assert f"(default: {getattr(FilterSettings(), field)})" in help_text, option
    assert actions["filters"].default == FilterSettings().kind
    assert actions["episodes"].default == EpisodeSettings().episodes
    assert actions["start_margin"].default == EpisodeSettings().start_margin
    assert math.isclose(float(f"{FilterSettings().gamma:g}"), DEFAULT_GAMMA)


