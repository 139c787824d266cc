"""Verification statistics: violations, delta-level, the scenario guarantee, confidence intervals.

Definitions follow ../shared/REFERENCE.md section 4 (the seed paper, DeepReach's verification code,
and Lin & Bansal's scenario optimisation):

* violation kind 1 ("false safe"): ``V(x, T) > 0`` but the rollout collides;
* violation kind 2 ("false unsafe"): ``V(x, T) <= 0`` but the rollout never collides;
* collision rate: every sampled state whose rollout collides (what the seed authors' code calls the
  violation rate; floored by the true BRT's volume fraction);
* delta-level: the largest ``V(x, T)`` among sampled states whose rollout collides, floored at 0
  (``{V > 0}`` is the least a value function claims safe); ``delta_raw`` keeps the unfloored value;
* scenario guarantee: with ``k`` failures among ``N`` fresh states from ``{V > delta}``, with
  confidence ``1 - beta`` the unsafe fraction of that set is at most ``eps``, the ``1 - beta``
  quantile of ``Beta(k + 1, N - k)``.
"""

from __future__ import annotations

import math

import torch


def _log_binomial_cdf(k: int, n: int, eps: torch.Tensor) -> torch.Tensor:
    """``log P(Bin(n, eps) <= k)`` for a batch of ``eps`` in (0, 1), in float64, without a loop."""
    i = torch.arange(k + 1, dtype=torch.float64)
    log_choose = math.lgamma(n + 1) - torch.lgamma(i + 1) - torch.lgamma(n - i + 1)
    e = eps.reshape(-1, 1)
    terms = log_choose + i * torch.log(e) + (n - i) * torch.log1p(-e)
    return torch.logsumexp(terms, dim=-1).reshape(eps.shape)


def scenario_epsilon(k: int, n: int, beta: float = 1e-16) -> float:
    """The ``1 - beta`` quantile of ``Beta(k + 1, n - k)``: eps with ``P(Bin(n, eps) <= k) = beta``.

    Solved by bisection on ``log eps`` of the binomial tail in log space, which stays accurate for
    ``beta`` as small as 1e-300. ``k = 0`` gives ``1 - beta^(1/n)``.
    """
    for name, v in (("k", k), ("n", n)):
        if isinstance(v, bool) or not isinstance(v, int):
            raise ValueError(f"{name} must be an integer, got {v!r}")
    if n < 1 or not 0 <= k < n:
        raise ValueError(f"need 0 <= k < n and n >= 1, got k={k}, n={n}")
    if not (0.0 < beta < 1.0):
        raise ValueError(f"beta must lie in (0, 1), got {beta!r}")
    target = math.log(beta)
    lo, hi = math.log(1e-300), math.log1p(-1e-16)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        value = float(_log_binomial_cdf(k, n, torch.tensor(math.exp(mid), dtype=torch.float64)))
        if value > target:  # the tail is still too likely: eps must grow
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-13:
            break
    return math.exp(hi)


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default); (0, 1) when ``n = 0``."""
    if n <= 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def violation_statistics(initial_value: torch.Tensor, collided: torch.Tensor) -> dict[str, float]:
    """The paper's violations (both kinds, and together), the collision rate and the delta-level."""
    if initial_value.shape != collided.shape or initial_value.ndim != 1:
        raise ValueError(f"values {tuple(initial_value.shape)} and outcomes {tuple(collided.shape)} must be (N,)")
    n = int(collided.numel())
    if n == 0:
        raise ValueError("no states to compute statistics on")
    v = initial_value.double()
    collided = collided.bool()
    false_safe = int(((v > 0) & collided).sum())
    false_unsafe = int(((v <= 0) & ~collided).sum())
    failures = v[collided]
    delta_raw = float(failures.max()) if failures.numel() else -math.inf
    return {
        "samples": n,
        "violation_rate": (false_safe + false_unsafe) / n,
        "false_safe_rate": false_safe / n,
        "false_unsafe_rate": false_unsafe / n,
        "collision_rate": int(collided.sum()) / n,
        "delta_raw": delta_raw,
        "delta": max(0.0, delta_raw),
        "safe_fraction": float((v > max(0.0, delta_raw)).double().mean()),
    }


def containment_statistics(union_values: torch.Tensor, learned_values: torch.Tensor) -> dict[str, float]:
    """How much of the union of pairwise BRTs a learned value misses.

    Every state in the union (``union <= 0``) is in the true BRT, so a learned value that calls such a
    state safe (``V > 0``) is provably wrong there. Returns that fraction of the sampled states with
    a 95 % Wilson interval, and the union's own fraction for scale.
    """
    if union_values.shape != learned_values.shape:
        raise ValueError(f"shapes differ: {tuple(union_values.shape)} vs {tuple(learned_values.shape)}")
    n = int(union_values.numel())
    missed = int(((union_values <= 0) & (learned_values > 0)).sum())
    low, high = wilson_interval(missed, n)
    return {
        "containment_miss_rate": missed / n,
        "containment_ci_low": low,
        "containment_ci_high": high,
        "union_fraction": float((union_values <= 0).double().mean()),
    }
