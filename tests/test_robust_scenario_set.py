"""Robust scenario verification (Lin & Bansal, L4DC 2024, Thm 2): search on one sample, check on another."""

from __future__ import annotations

import importlib
import math

import pytest
import torch

from safety.verification.metrics import binomial_bound_holds, robust_level_search, scenario_epsilon
from safety.verification.verify import VerifySettings, sample_states, verify


def _synthetic(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Values uniform in [-1, 1]; failures certain below 0 and ever rarer above it."""
    g = torch.Generator().manual_seed(seed)
    v = torch.rand(n, generator=g) * 2 - 1
    p = torch.where(v < 0, torch.full_like(v, 0.9), 2e-2 * torch.exp(-5 * v))
    return v, torch.rand(n, generator=g) < p


def test_search_returns_the_largest_bounded_set():
    v, failed = _synthetic(50_000)
    level, n, k = robust_level_search(v, failed, target_eps=0.01, beta=1e-6)
    assert n == int((v > level).sum()) and k == int((failed & (v > level)).sum())
    assert scenario_epsilon(k, n, 1e-6) <= 0.01  # the bound holds on the found set
    order = torch.argsort(v, descending=True)
    cumulative = torch.cumsum(failed[order].long(), 0)
    for extra in (20, 200, 2000):  # a larger set breaks it
        m = n + extra
        assert not binomial_bound_holds(int(cumulative[m - 1]), m, 0.01, 1e-6)


def test_search_allows_failures_where_the_zero_violation_level_cannot():
    v, failed = _synthetic(50_000)
    level, n, k = robust_level_search(v, failed, target_eps=0.01, beta=1e-6)
    zero_violation_level = float(v[failed].max())  # the delta-level: no failure above it
    assert k > 0 and level < zero_violation_level  # a larger set than delta's, failures allowed


def test_too_few_samples_find_no_level():
    v, failed = _synthetic(1000)
    need = math.log(1 / 1e-16) / 3e-4
    assert len(v) < need and robust_level_search(v, failed, 3e-4, 1e-16) is None
    with pytest.raises(ValueError, match="target_eps"):
        robust_level_search(v, failed, 0.0, 1e-16)


def test_verify_reports_the_robust_columns_from_a_fresh_sample(air3d_grid):
    states = sample_states(air3d_grid.system, 400, 0)
    settings = VerifySettings(samples=400, scenario_samples=0, robust_samples=3000, target_eps=0.05, dt=0.01)
    row = verify(air3d_grid, states, settings, progress=False)
    assert row["robust_samples"] == 3000 and row["robust_target_eps"] == 0.05
    assert math.isfinite(row["robust_level"]) and 0.5 < row["robust_scenario_volume"] < 1.0
    assert isinstance(row["robust_failures"], int)
    assert row["robust_eps"] == pytest.approx(scenario_epsilon(row["robust_failures"], 3000, settings.beta))
    skipped = verify(
        air3d_grid, states, VerifySettings(samples=400, scenario_samples=0, robust_samples=0, dt=0.01), progress=False
    )
    assert "robust_level" not in skipped


def test_verify_says_why_when_no_level_qualifies(air3d_grid):
    states = sample_states(air3d_grid.system, 200, 0)
    settings = VerifySettings(samples=200, scenario_samples=0, robust_samples=500, dt=0.01)
    row = verify(air3d_grid, states, settings, progress=False)
    assert "needs at least" in row["robust_error"] and math.isnan(row["robust_level"])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"target_eps": 0.0}, "target_eps"),
        ({"target_eps": 1.5}, "target_eps"),
        ({"robust_samples": -1}, "robust_samples"),
    ],
)
def test_bad_robust_settings_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        VerifySettings(**kwargs)


def _counting(monkeypatch) -> list[int]:
    """Count the states every rollout of a verification simulates."""
    verify_module = importlib.import_module("safety.verification.verify")  # the package's `verify` is the function

    counts: list[int] = []
    real = verify_module.rollout

    def counted(vf, states, *args, **kwargs):
        counts.append(int(states.shape[0]))
        return real(vf, states, *args, **kwargs)

    monkeypatch.setattr(verify_module, "rollout", counted)
    return counts


def test_a_shared_delta_check_reuses_the_robust_checks_states_and_counts_the_same_failures(air3d_grid, monkeypatch):
    from safety.verification.rollout import rollout
    from safety.verification.verify import sample_superlevel_set

    counts = _counting(monkeypatch)
    states = sample_states(air3d_grid.system, 400, 0)
    common = dict(samples=400, scenario_samples=1000, robust_samples=3000, target_eps=0.05, dt=0.01)
    alone = verify(air3d_grid, states, VerifySettings(**common), progress=False)
    rolled_alone = sum(counts)
    counts.clear()
    shared = verify(air3d_grid, states, VerifySettings(**common, share_samples=True), progress=False)
    used = shared["scenario_reused"]
    assert alone["robust_level"] <= alone["delta"] and 0 < used <= 1000
    # the same statistics and robust columns; only the delta-level's check differs, by its reuse
    for key in ("delta", "violation_rate", "robust_level", "robust_failures", "robust_eps", "scenario_volume"):
        assert shared[key] == alone[key]
    assert shared["scenario_states"] == 1000 and sum(counts) == rolled_alone - used
    # its failures are those of the robust check's first `used` states in {V > delta}, plus the top-up's
    horizon = air3d_grid.system.horizon
    check, _ = sample_superlevel_set(air3d_grid, alone["robust_level"], 3000, 0 + 3, horizon)
    outcome = rollout(air3d_grid, check, dt=0.01, progress=False)
    inside = outcome.oriented_value > alone["delta"]
    expected = int(outcome.failed[inside][:used].sum())
    if used < 1000:
        top_up, _ = sample_superlevel_set(air3d_grid, alone["delta"], 1000 - used, 0 + 1, horizon)
        expected += int(rollout(air3d_grid, top_up, dt=0.01, progress=False).failed.sum())
    assert shared["scenario_failures"] == expected
    assert shared["eps"] == pytest.approx(scenario_epsilon(expected, 1000, 1e-16))


def test_a_robust_level_above_delta_shares_nothing(air3d_grid, monkeypatch):
    verify_module = importlib.import_module("safety.verification.verify")  # the package's `verify` is the function

    states = sample_states(air3d_grid.system, 400, 0)
    common = dict(samples=400, scenario_samples=500, robust_samples=3000, target_eps=0.05, dt=0.01, share_samples=True)
    delta = verify(air3d_grid, states, VerifySettings(**common), progress=False)["delta"]
    # a level above delta: its superlevel set misses part of {V > delta}, so its states are not reused
    monkeypatch.setattr(verify_module, "robust_level_search", lambda v, f, eps, beta: (delta + 0.05, 1, 0))
    row = verify(air3d_grid, states, VerifySettings(**common), progress=False)
    assert row["robust_level"] == delta + 0.05 and row["scenario_reused"] == 0 and row["scenario_states"] == 500


def test_share_samples_must_be_a_bool():
    with pytest.raises(ValueError, match="share_samples"):
        VerifySettings(share_samples="yes")
