"""A branch-and-bound verifier's progress on disk, so that a stopped run continues where it stopped.

:func:`safety.formal.verifier.certify` given a progress file (``reach certify ... --resume FILE.npz``) saves its
state there atomically every :data:`SAVE_EVERY_S` seconds and when it stops: the boxes still queued,
the boxes decided with their status and backup input, the counterexamples, and the boxes handled and
seconds spent so far. Started again with the same file, it loads that state and goes on; a run that
had finished returns its result at once.

The file is an ``.npz`` of arrays and one JSON header (loading runs no code). It records what the
proof depends on (the value function's fingerprint, the system, and the settings that define the
proof: level, time-to-go, ``dt``, integrator and the cover); a file made for anything else is refused
naming the difference, never continued. The effort settings (``batch``, ``max_boxes``,
``max_seconds``) may change between runs: ``max_boxes`` counts every box handled across the runs,
``max_seconds`` the wall time of one run. Boxes still queued when a run stops count as unknown in
its result: an unfinished run is never reported as proven.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from reach.atomic import atomic_path

__all__ = ["PROOF_FIELDS", "SAVE_EVERY_S", "VerifierProgress", "load_progress", "save_progress"]

FORMAT = "reach-certify-progress/1"

#: the settings a proof depends on: a progress file made with others is refused
PROOF_FIELDS = (
    "level",
    "time_to_go",
    "dt",
    "integrator",
    "disturbance_splits",
    "initial_splits",
    "min_relative_width",
    "escape_margin",
    "band_min_relative_width",
    "closure_scale",  # above 1 the verifier proves without the escape set (the closure's lies beyond)
)
#: proof fields that files written before them lack, and what that meant
_BEFORE = {"closure_scale": 1}

#: seconds between saves of a running verifier's progress
SAVE_EVERY_S = 30.0

_ARRAYS = ("queue_lo", "queue_hi", "done_lo", "done_hi", "done_status", "done_backup")


@dataclass
class VerifierProgress:
    """The verifier's state between batches: queued boxes, decided boxes (corners, status, backup
    input index), counterexamples, boxes handled and seconds spent over every run so far."""

    queue_lo: torch.Tensor
    queue_hi: torch.Tensor
    done_lo: torch.Tensor
    done_hi: torch.Tensor
    done_status: torch.Tensor
    done_backup: torch.Tensor
    counterexamples: list[dict] = field(default_factory=list)
    handled: int = 0
    seconds: float = 0.0


def _header(settings: dict[str, Any], system: dict, fingerprint: str) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "proof": {k: settings[k] for k in PROOF_FIELDS},
        "system": system,
        "fingerprint": fingerprint,
    }


def save_progress(
    path: str | Path, progress: VerifierProgress, settings: dict[str, Any], system: dict, fingerprint: str
) -> None:
    """Write ``progress`` to ``path`` atomically (an interrupted write leaves the previous save)."""
    header = {
        **_header(settings, system, fingerprint),
        "counterexamples": progress.counterexamples,
        "handled": progress.handled,
        "seconds": progress.seconds,
    }
    arrays = {name: getattr(progress, name).cpu().numpy() for name in _ARRAYS}
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, header=np.array(json.dumps(header)), **arrays)


def load_progress(
    path: str | Path, settings: dict[str, Any], system: dict, fingerprint: str
) -> VerifierProgress | None:
    """The progress saved at ``path`` (None where no file is there yet); ``ValueError`` naming what
    differs where it was made for another value function, system or proof."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(str(data["header"]))
            arrays = {name: torch.from_numpy(np.array(data[name])) for name in _ARRAYS}
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a verifier progress file ({err})") from None
    found = header.get("format") if isinstance(header, dict) else None
    if found != FORMAT:
        raise ValueError(f"{path}: not a verifier progress file (format {found!r})")
    ours = _header(settings, system, fingerprint)
    if header["fingerprint"] != fingerprint:
        raise ValueError(
            f"{path}: the progress of another value function ({str(header['fingerprint'])[:12]}..., not "
            f"{fingerprint[:12]}...); give another progress file to start over"
        )
    if header["system"] != system:
        theirs = header["system"].get("name") if isinstance(header["system"], dict) else header["system"]
        what = f"{theirs}, not {system['name']}" if theirs != system["name"] else f"{theirs} with other parameters"
        raise ValueError(f"{path}: the progress of another system ({what})")
    saved = header["proof"]
    differ = [
        f"{k} {saved.get(k, _BEFORE.get(k))!r}, not {v!r}"
        for k, v in ours["proof"].items()
        if saved.get(k, _BEFORE.get(k)) != v
    ]
    if differ:
        raise ValueError(f"{path}: the progress of another proof ({'; '.join(differ)}); give another progress file")
    return VerifierProgress(
        **arrays,
        counterexamples=list(header["counterexamples"]),
        handled=int(header["handled"]),
        seconds=float(header["seconds"]),
    )
