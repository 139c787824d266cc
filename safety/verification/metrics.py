"""Verification statistics: violations, delta-level, the scenario guarantee, confidence intervals.

Definitions follow docs/concepts.md, "Measuring a learned value function" (the seed paper,
DeepReach's verification code, and Lin & Bansal's scenario optimisation):

* violation kind 1 ("false safe"): ``V(x, T) > 0`` but the rollout collides;
* violation kind 2 ("false unsafe"): ``V(x, T) <= 0`` but the rollout never collides;
* collision rate: every sampled state whose rollout collides (what the seed authors' code calls the
  violation rate; floored by the true BRT's volume fraction);
* delta-level: the largest ``V(x, T)`` among sampled states whose rollout collides, floored at 0
  (``{V > 0}`` is the least a value function claims safe); ``delta_raw`` keeps the unfloored value;
* scenario guarantee: with ``k`` failures among ``N`` fresh states from ``{V > delta}``, with
  confidence ``1 - beta`` the unsafe fraction of that set is at most ``eps``, the ``1 - beta``
  quantile of ``Beta(k + 1, N - k)``;
* robust scenario level (Lin & Bansal, L4DC 2024, Thm 2): the same bound with failures allowed. For a
  target ``eps``, the lowest level (largest set ``{V > level}``) whose sampled states, ``n`` of them
  with ``k`` failures, keep ``P(Bin(n, eps) <= k) <= beta`` (:func:`robust_level_search`).

Reach and reach-avoid problems mirror all of it on the other side of zero: a value function claims
*reachable* where ``V < 0`` (the boundary, of measure zero, counts as no claim), a rollout *fails*
when it does not reach the target in time without a collision, and the scenario set is
``{V < -delta}``. The functions here take values *oriented* so that ``> 0`` is the claim
(:meth:`~reach.systems.problem.ProblemKind.orient`: ``-V`` for reach kinds) and the per-state
failures, so one implementation serves every kind; :func:`violation_statistics` names its columns
for the kind (:data:`KIND_COLUMNS`).
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


def binomial_bound_holds(k: int, n: int, eps: float, beta: float) -> bool:
    """Whether ``k`` failures among ``n`` samples bound ``eps`` at confidence ``1 - beta``:
    ``P(Bin(n, eps) <= k) <= beta`` (equivalently ``scenario_epsilon(k, n, beta) <= eps``)."""
    if n < 1 or k >= n:
        return False
    return float(_log_binomial_cdf(k, n, torch.tensor(eps, dtype=torch.float64))) <= math.log(beta)


def robust_level_search(
    values: torch.Tensor, failed: torch.Tensor, target_eps: float, beta: float, candidates: int = 256
) -> tuple[float, int, int] | None:
    """The lowest level whose superlevel set ``{V > level}`` the samples bound at ``target_eps``.

    ``values`` and ``failed`` are ``V(x, T)`` and rollout outcomes of states drawn uniformly from
    the domain, so those in ``{V > level}`` are uniform on that set. Among candidate levels (the
    sampled values themselves, on a coarse grid of ``candidates`` set sizes, then refined between the
    two best), returns ``(level, n, k)`` for the largest set where :func:`binomial_bound_holds`, or
    None when no set qualifies (too few samples for ``target_eps``: ``k = 0`` needs
    ``n >= ln(1 / beta) / target_eps``). A level found by this search must be checked on a fresh
    sample before it means anything (:func:`safety.verification.verify.verify` does).
    """
    if not (0.0 < target_eps < 1.0):
        raise ValueError(f"target_eps must lie in (0, 1), got {target_eps!r}")
    order = torch.argsort(values.double(), descending=True)
    v = values.double()[order]
    fails = torch.cumsum(failed[order].long(), 0)
    total = v.numel()

    def set_at(i: int) -> tuple[float, int, int]:
        """The set of the ``i`` highest values: its level (the next value down) and its n, k."""
        level = float(v[i]) if i < total else -math.inf
        n = int(torch.searchsorted(-v, -torch.tensor(level, dtype=torch.float64), right=False))  # #{V > level}
        return level, n, int(fails[n - 1]) if n else 0

    def best_in(sizes: list[int]) -> int | None:
        ok = []
        for i in sizes:
            _, n, k = set_at(i)
            if binomial_bound_holds(k, n, target_eps, beta):
                ok.append(i)
        return max(ok) if ok else None

    coarse = sorted({max(1, round(total * j / candidates)) for j in range(1, candidates + 1)})
    best = best_in(coarse)
    if best is None:
        return None
    above = next((c for c in coarse if c > best), total)
    fine = sorted({round(best + (above - best) * j / candidates) for j in range(candidates + 1)})
    best = best_in(fine) or best
    return set_at(best)


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default); (0, 1) when ``n = 0``."""
    if n <= 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # the bounds are exact at the ends: rounding would leave 2.8e-17 above a rate of 0
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return low, high


#: per kind of problem, the names :func:`violation_statistics` gives its columns: a wrong claim on
#: the good side, a wrong claim on the other side, the failed rollouts, and the share of the states
#: in the scenario set (``{V > delta}`` for avoid, ``{V < -delta}`` for reach kinds)
KIND_COLUMNS = {
    "avoid": ("false_safe_rate", "false_unsafe_rate", "collision_rate", "safe_fraction"),
    "reach": ("false_reachable_rate", "false_unreachable_rate", "failure_rate", "reachable_fraction"),
    "reach-avoid": ("false_reachable_rate", "false_unreachable_rate", "failure_rate", "reachable_fraction"),
}


def violation_statistics(
    initial_value: torch.Tensor, failed: torch.Tensor, kind: str = "avoid", collided: torch.Tensor | None = None
) -> dict[str, float]:
    """The paper's violations (both ways, apart and together), the failure rate and the delta-level.

    ``initial_value`` is ``V(x, T)`` *oriented* so that ``> 0`` is the claim (``V`` for avoid, ``-V``
    for reach kinds) and ``failed`` the rollouts that failed their task. The columns are named for
    ``kind`` (:data:`KIND_COLUMNS`); a reach-avoid row also gets ``collision_rate``, the rollouts that
    left the constraint set (``collided``).
    """
    if kind not in KIND_COLUMNS:
        raise ValueError(f"kind must be one of {tuple(KIND_COLUMNS)}, got {kind!r}")
    if initial_value.shape != failed.shape or initial_value.ndim != 1:
        raise ValueError(f"values {tuple(initial_value.shape)} and outcomes {tuple(failed.shape)} must be (N,)")
    n = int(failed.numel())
    if n == 0:
        raise ValueError("no states to compute statistics on")
    v = initial_value.double()
    failed = failed.bool()
    false_claim = int(((v > 0) & failed).sum())
    false_denial = int(((v <= 0) & ~failed).sum())
    failures = v[failed]
    delta_raw = float(failures.max()) if failures.numel() else -math.inf
    claim, denial, failure, in_set = KIND_COLUMNS[kind]
    row: dict[str, float] = {
        "samples": n,
        "violation_rate": (false_claim + false_denial) / n,
        claim: false_claim / n,
        denial: false_denial / n,
        failure: int(failed.sum()) / n,
        "delta_raw": delta_raw,
        "delta": max(0.0, delta_raw),
        in_set: float((v > max(0.0, delta_raw)).double().mean()),
    }
    if kind == "reach-avoid" and collided is not None:
        row["collision_rate"] = int(collided.bool().sum()) / n
    return row


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
