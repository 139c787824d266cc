"""Whether a shipped model meets its kind's trust bar: a verdict computed from its card, never typed.

A value function earns its use as a filter's default by its card's figures (``reach evaluate`` on
fresh states, recorded by ``benchmarks/make_pretrained.py``):

- **wrong claims** at most :data:`MAX_WRONG_CLAIMS` (0.05 % of the box): states the model calls safe
  (avoid: ``false_safe_rate``) or reachable (reach kinds: ``false_reachable_rate``) from which its own
  rollouts fail, on at least :data:`MIN_SAMPLES` states;
- **a scenario set** with its ``eps``: the delta-level set ``{V > delta}`` (reach kinds:
  ``{V < -delta}``) bounded on fresh samples, and, where the card drew :data:`ROBUST_FROM` or more
  fresh states for it, the robust scenario set as well (Lin & Bansal): a statistical bound, not a
  certificate (that word is for :mod:`safety.formal`).

The evaluation judged is the one of the filter's default: the card's ``filter_source`` where it
names one (else the bare model), under the switch filter's default backup input (:data:`FILTER_POLICY`)
where the card evaluated it so, else its main evaluation; the verdict names the one it used.
Nothing reads a stored verdict: :func:`trust_verdict` recomputes it from the figures each time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

#: the most wrong claims (a share of the box's states) a trusted model makes
MAX_WRONG_CLAIMS = 5e-4
#: the fewest fresh states the wrong-claim rate must come from
MIN_SAMPLES = 100_000
#: fresh states from which a card's scenario set must be the robust one too
ROBUST_FROM = 1_000_000
#: the switch filter's default backup input per kind of problem (``safety.filters.settings``: greedy
#: for avoid, the gradient's ``u*`` for reach kinds, which refuse the greedy input)
FILTER_POLICY = {"avoid": "greedy", "reach": "gradient", "reach-avoid": "gradient"}
#: the wrong-claim column per kind (``safety.verification.metrics.KIND_COLUMNS``' first)
WRONG_CLAIMS = {"avoid": "false_safe_rate", "reach": "false_reachable_rate", "reach-avoid": "false_reachable_rate"}


@dataclass(frozen=True)
class Verdict:
    """A model's standing against the trust bar, with the figures it rests on."""

    #: whether every condition holds
    passes: bool
    #: the evaluation judged: its label and policy
    evaluation: str
    #: the wrong-claim rate and how many states it comes from (None where the card has none)
    wrong_claims: float | None
    samples: int | None
    #: the scenario set, in words ("0.905 of the box at eps 4.9e-04", "none")
    scenario: str
    #: each condition that fails, in words (empty when it passes)
    failures: tuple[str, ...] = ()

    def line(self) -> str:
        """One line for listings and refusals."""
        claims = "no wrong-claim rate" if self.wrong_claims is None else f"wrong claims {100 * self.wrong_claims:.3g} %"
        states = "" if self.samples is None else f" on {self.samples:,} states"
        head = "passes" if self.passes else "fails (" + "; ".join(self.failures) + ")"
        return f"{head}: {claims}{states}, scenario set {self.scenario} [{self.evaluation}]"


def _finite(value: Any) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if math.isfinite(out) else None


def _label(entry: dict[str, Any], source: str) -> str:
    label, policy = str(entry.get("label", source)), str(entry.get("policy", "gradient"))
    return label if f"{policy} policy" in label else f"{label}, {policy} policy"


def judged_evaluation(card: Any, kind: str) -> tuple[str, dict[str, Any]]:
    """``(label, evaluation)``: the card's evaluation of its filter's default source and policy (see
    the module docstring), else its main evaluation."""
    source = card.filter_source or f"pretrained:{card.name}"
    policy = FILTER_POLICY[kind]
    same_source = [e for e in card.also_evaluated if e.get("source") == source]
    chosen = [e for e in same_source if e.get("policy", "gradient") == policy]
    if chosen:  # the largest fresh sample of those: the card's protocol over a quicker look
        entry = max(chosen, key=lambda e: (_finite(e.get("metrics", {}).get("scenario_states")) or 0.0))
        return _label(entry, source), entry
    main_policy = card.evaluation.get("policy", "gradient")
    if not card.filter_source:
        return f"the card's evaluation, {main_policy} policy", card.evaluation
    if same_source:
        return _label(same_source[0], source), same_source[0]
    return f"the bare model's evaluation, {main_policy} policy", card.evaluation


def trust_verdict(card: Any, kind: str) -> Verdict:
    """The :class:`Verdict` of ``card`` (a :class:`~training.pretrained.ModelCard`) for a system of
    ``kind`` (``"avoid"``, ``"reach"``, ``"reach-avoid"``), from its figures alone."""
    if kind not in WRONG_CLAIMS:
        raise ValueError(f"kind must be one of {tuple(WRONG_CLAIMS)}, got {kind!r}")
    label, evaluation = judged_evaluation(card, kind)
    metrics = dict(evaluation.get("metrics", {}))
    failures = []
    wrong = _finite(metrics.get(WRONG_CLAIMS[kind]))
    samples = metrics.get("samples", evaluation.get("samples"))
    samples = int(samples) if _finite(samples) is not None else None
    if wrong is None:
        failures.append("no wrong-claim rate on the card")
    elif wrong > MAX_WRONG_CLAIMS:
        failures.append(f"wrong claims {100 * wrong:.3g} % > {100 * MAX_WRONG_CLAIMS:g} %")
    if samples is None or samples < MIN_SAMPLES:
        failures.append(f"{samples or 0:,} states < {MIN_SAMPLES:,}")
    volume, eps = _finite(metrics.get("scenario_volume")), _finite(metrics.get("eps"))
    robust, robust_eps = _finite(metrics.get("robust_scenario_volume")), _finite(metrics.get("robust_eps"))
    fresh = _finite(metrics.get("scenario_states")) or 0.0
    if robust is not None and robust > 0 and robust_eps is not None:
        scenario = f"robust {robust:.3g} of the box at eps {robust_eps:.2g}"
    elif volume is not None and volume > 0 and eps is not None:
        scenario = f"{volume:.3g} of the box at eps {eps:.2g}"
        if fresh >= ROBUST_FROM:
            failures.append(f"no robust scenario set from {int(fresh):,} fresh states")
    else:
        scenario = "none"
        failures.append("no scenario set")
    return Verdict(not failures, label, wrong, samples, scenario, tuple(failures))


__all__ = [
    "FILTER_POLICY",
    "MAX_WRONG_CLAIMS",
    "MIN_SAMPLES",
    "ROBUST_FROM",
    "Verdict",
    "judged_evaluation",
    "trust_verdict",
]
