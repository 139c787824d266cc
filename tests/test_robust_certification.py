"""Robust scenario certification (Lin & Bansal, L4DC 2024, Thm 2): search on one sample, certify on another."""

from __future__ import annotations

import math

import pytest
import torch

from safety.metrics import binomial_bound_holds, robust_level_search, scenario_epsilon
from safety.verify import VerifySettings, sample_states, verify


def _synthetic(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Values uniform in [-1, 1]; failures certain below 0 and ever rarer above it."""
    g = torch.Generator().manual_seed(seed)
    v = torch.rand(n, generator=g) * 2 - 1
    p = torch.where(v < 0, torch.full_like(v, 0.9), 2e-2 * torch.exp(-5 * v))
    return v, torch.rand(n, generator=g) < p


def test_search_returns_the_largest_certified_set():
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


def test_verify_reports_the_robust_columns_from_a_fresh_certification(air3d_grid):
    states = sample_states(air3d_grid.system, 400, 0)
    settings = VerifySettings(samples=400, certify_samples=0, robust_samples=3000, target_eps=0.05, dt=0.01)
    row = verify(air3d_grid, states, settings, progress=False)
    assert row["robust_samples"] == 3000 and row["robust_target_eps"] == 0.05
    assert math.isfinite(row["robust_level"]) and 0.5 < row["robust_certified_volume"] < 1.0
    assert isinstance(row["robust_failures"], int)
    assert row["robust_eps"] == pytest.approx(scenario_epsilon(row["robust_failures"], 3000, settings.beta))
    skipped = verify(
        air3d_grid, states, VerifySettings(samples=400, certify_samples=0, robust_samples=0, dt=0.01), progress=False
    )
    assert "robust_level" not in skipped


def test_verify_says_why_when_no_level_qualifies(air3d_grid):
    states = sample_states(air3d_grid.system, 200, 0)
    settings = VerifySettings(samples=200, certify_samples=0, robust_samples=500, dt=0.01)
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
