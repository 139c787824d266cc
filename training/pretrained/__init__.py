"""Value networks that ship with the package, each with a model card.

A pretrained model is two package-data files in this directory: the model, and ``NAME.card.json``,
its model card. The model is ``NAME.pt``, a reach checkpoint without optimizer state (read with
``weights_only=True`` and checked against its SHA-256 digest like any checkpoint), or, for a card
whose ``format`` is ``"grid"``, ``NAME.npz``, a grid solution (read without pickle, checked the
same way): ``pretrained:relativepair`` is DeepReach's two-car pair problem on a compact grid, whose
union of pairwise BRTs caps the N-car networks. The card:

- ``system``: the registered system it was trained (or solved) for; ``env_ids``: the Gymnasium ids
  whose filter uses it when no value function is given; ``filter_source``: what those filters load
  instead of the bare model, if anything (the 9D model's is the model capped by the pair grid's union);
- ``training``: the command that trained it, the commit, wall time, steps and hardware;
- ``evaluation``: the ``reach evaluate`` command, its sample sizes and the metrics it printed;
- ``also_evaluated``: the same file scored other ways, each a labelled evaluation with its
  ``source`` and ``policy`` (e.g. capped by the pairwise union, rolled out under the greedy policy
  the switch filter applies), so a card states what the filters built on it were measured to do;
- ``sha256``: the digest of ``NAME.pt``, so a swapped or damaged file is refused by name.

Anything that takes a value function takes ``"pretrained:NAME"`` (:data:`PREFIX`), through
:func:`safety.value_loading.load_value_function`. ``reach pretrained`` lists the cards.
Maintainers add or replace a model with ``benchmarks/make_pretrained.py``.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from reach.json_files import read_json
from reach.result_columns import current_names
from reach.systems import make_system
from training.pretrained.verdict import Verdict, trust_verdict

#: a source naming a shipped model: ``"pretrained:air3d"``
PREFIX = "pretrained:"
#: where the model files live (package data)
DIRECTORY = Path(__file__).resolve().parent
CARD_SUFFIX = ".card.json"


@dataclass(frozen=True)
class ModelCard:
    """What a shipped model is, how it was made and how it scored (see the module docstring)."""

    name: str
    system: str
    env_ids: tuple[str, ...]
    summary: str
    training: dict[str, Any] = field(default_factory=dict)
    evaluation: dict[str, Any] = field(default_factory=dict)
    also_evaluated: tuple[dict[str, Any], ...] = ()
    sha256: str = ""
    format: str = "network"
    filter_source: str = ""

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str) -> ModelCard:
        try:
            return cls(
                name=str(data["name"]),
                system=str(data["system"]),
                env_ids=tuple(str(e) for e in data.get("env_ids", ())),
                summary=str(data.get("summary", "")),
                training=dict(data.get("training", {})),
                evaluation=dict(data.get("evaluation", {})),
                also_evaluated=tuple(dict(e) for e in data.get("also_evaluated", ())),
                sha256=str(data["sha256"]),
                format=_check_format(str(data.get("format", "network")), where),
                filter_source=str(data.get("filter_source", "")),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{where}: not a model card ({type(err).__name__}: {err})") from err

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "env_ids": list(self.env_ids), "also_evaluated": list(self.also_evaluated)}

    @property
    def verdict(self) -> Verdict:
        """Whether this model meets its kind's trust bar, computed from the figures above
        (:func:`~training.pretrained.verdict.trust_verdict`)."""
        return trust_verdict(self, make_system(self.system).kind)

    @property
    def metrics(self) -> dict[str, Any]:
        """The ``reach evaluate`` row the card records (empty before evaluation)."""
        return dict(self.evaluation.get("metrics", {}))

    def describe(self) -> str:
        """A few lines for ``reach pretrained``: what, how trained, how it scored."""
        t, e, m = self.training, self.evaluation, self.metrics
        lines = [f"{PREFIX}{self.name}  ({self.system}; envs: {', '.join(self.env_ids) or '-'})", f"  {self.summary}"]
        lines.append(f"  trust bar: {self.verdict.line()}")
        if t and self.format == "grid":
            shape = "x".join(str(n) for n in t.get("grid", ())) or "?"
            lines.append(f"  solved: on a {shape} grid, {t.get('hardware', '?')}")
        elif t:
            lines.append(
                f"  trained: {t.get('steps', '?')} steps, {_minutes(t.get('wall_time_s'))} on {t.get('hardware', '?')}"
            )  # the commit stays in the card (and in --json), not in what users read
            if t.get("command"):
                lines.append(f"    {t['command']}")
        if m:
            lines.append(f"  evaluated on {e.get('samples', '?')} states: {_shown(m)}")
            if e.get("command"):
                lines.append(f"    {e['command']}")
        for other in self.also_evaluated:
            what = f"{other.get('label', '?')} [{other.get('source', '?')}, {other.get('policy', 'gradient')} policy]"
            lines.append(f"  also, {what}, on {other.get('samples', '?')} states: {_shown(other.get('metrics', {}))}")
            if other.get("command"):
                lines.append(f"    {other['command']}")
        return "\n".join(lines)


#: (row key, label, scale) shown by :meth:`ModelCard.describe`
_CARD_METRICS = (
    ("violation_rate", "violation %", 100.0),
    ("false_safe_rate", "false safe %", 100.0),
    ("false_reachable_rate", "false reachable %", 100.0),
    ("failure_rate", "failure %", 100.0),
    ("collision_rate", "collision %", 100.0),
    ("delta", "delta", 1.0),
    ("scenario_volume", "scenario vol.", 1.0),
    ("robust_scenario_volume", "robust vol.", 1.0),
    ("robust_eps", "at eps", 1.0),
    ("iou_volume", "IoU vol.", 1.0),
    ("containment_miss_rate", "misses union %", 100.0),
)


def _shown(metrics: dict[str, Any]) -> str:
    return ", ".join(
        f"{label} {_number(metrics.get(key), scale)}"
        for key, label, scale in _CARD_METRICS
        if metrics.get(key) is not None
    )


def _minutes(seconds: Any) -> str:
    return f"{float(seconds) / 60:.1f} min" if isinstance(seconds, (int, float)) else "?"


def _number(value: Any, scale: float) -> str:
    return f"{value * scale:.3g}" if isinstance(value, (int, float)) else str(value)


#: card ``format`` -> the model file's suffix
MODEL_SUFFIXES = {"network": ".pt", "grid": ".npz"}


def _check_format(value: str, where: str) -> str:
    if value not in MODEL_SUFFIXES:
        raise ValueError(f"{where}: format must be one of {sorted(MODEL_SUFFIXES)}, got {value!r}")
    return value


def names() -> list[str]:
    """The shipped models' names, sorted."""
    return sorted(p.name[: -len(CARD_SUFFIX)] for p in DIRECTORY.glob(f"*{CARD_SUFFIX}"))


def is_pretrained(source: Any) -> bool:
    """Whether ``source`` is a ``"pretrained:NAME"`` string."""
    return isinstance(source, str) and source.startswith(PREFIX)


def _check_name(name: str) -> str:
    available = names()
    if name not in available:
        raise ValueError(
            f"no pretrained model {name!r}; shipped: {', '.join(available) or 'none'} (reach pretrained lists them)"
        )
    return name


def card(name: str) -> ModelCard:
    """The model card of a shipped model; an unknown name raises ``ValueError`` listing the known ones."""
    path = DIRECTORY / f"{_check_name(name)}{CARD_SUFFIX}"
    data = current_names(read_json(path, "a model card"))
    return ModelCard.from_dict(data, str(path))


def cards() -> list[ModelCard]:
    """Every shipped model's card, by name."""
    return [card(n) for n in names()]


def file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def checkpoint_path(source: str) -> Path:
    """The model file of ``"pretrained:NAME"`` (or ``NAME``): its checkpoint ``.pt``, or its grid
    ``.npz`` for a grid card, after checking it is the file its card describes: a replaced or
    damaged file raises ``ValueError`` instead of loading."""
    name = source[len(PREFIX) :] if is_pretrained(source) else source
    c = card(name)
    path = DIRECTORY / f"{name}{MODEL_SUFFIXES[c.format]}"
    if not path.is_file():
        raise ValueError(f"{PREFIX}{name}: its model file {path} is missing from the installed package")
    if file_sha256(path) != c.sha256:
        raise ValueError(f"{PREFIX}{name}: {path} is not the file its model card describes (SHA-256 mismatch)")
    return path


def source_verdict(source: Any) -> Verdict | None:
    """The verdict of a source that names a shipped model (``"pretrained:NAME"``), else None: a value
    function of the user's own carries no verdict (using it is the user's choice)."""
    if not is_pretrained(source):
        return None
    return card(str(source)[len(PREFIX) :]).verdict


def card_for_env(env_id: str | None, system: Any) -> ModelCard | None:
    """The card of the model a filter on env ``env_id`` uses when given no value function: a card
    listing ``env_id`` wins; otherwise a model trained for a system of the same physics as ``system``
    (:meth:`~reach.systems.base.ControlAffineSystem.same_physics`); None where no model ships."""
    all_cards = cards()
    for c in all_cards:
        if env_id is not None and env_id in c.env_ids:
            return c
    wanted = make_system(system)
    for c in all_cards:
        if wanted.same_physics(make_system(c.system)):
            return c
    return None


def for_env(env_id: str | None, system: Any, allow_untrusted: bool = False) -> str:
    """The source a filter on env ``env_id`` uses when given no value function: ``"pretrained:NAME"``,
    or the card's ``filter_source`` where it names one (``"cap:pretrained:multivehicle9d,..."``).

    Nothing picks an untrusted model: where the card's :attr:`~ModelCard.verdict` fails the trust bar,
    ``ValueError`` names its figures and the opt-in, unless ``allow_untrusted``. No shipped model
    raises ``ValueError`` naming the env and the shipped models."""
    if not isinstance(allow_untrusted, bool):
        raise ValueError(f"allow_untrusted must be True or False, got {allow_untrusted!r}")
    found = card_for_env(env_id, system)
    if found is not None:
        verdict = found.verdict
        if not verdict.passes and not allow_untrusted:
            raise ValueError(
                f"{PREFIX}{found.name}, the shipped model for {env_id or found.system}, {verdict.line()}; pass "
                "allow_untrusted=True to filter with it anyway, or give your own value function"
            )
        return found.filter_source or PREFIX + found.name
    all_cards = cards()
    wanted = make_system(system)
    raise ValueError(
        f"no pretrained value function for env {env_id or '(no id)'} ({wanted.name}); shipped: "
        f"{', '.join(f'{c.name} ({c.system})' for c in all_cards) or 'none'}; pass a value function"
    )


__all__ = [
    "DIRECTORY",
    "PREFIX",
    "ModelCard",
    "Verdict",
    "card",
    "card_for_env",
    "cards",
    "checkpoint_path",
    "for_env",
    "is_pretrained",
    "names",
    "source_verdict",
    "trust_verdict",
]
