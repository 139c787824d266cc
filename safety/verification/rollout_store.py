"""Rollout outcomes kept on disk block by block, so that an interrupted verification resumes.

Certifying a 9D value function rolls out millions of states (the model card's protocol: 100k, then
1M fresh, then 1M + 1M for the robust level); under the greedy policy that is hours on a CPU. A
:class:`RolloutStore` saves each block of ``chunk_size`` states' outcomes (initial value, collided,
collision and decision times, work done) as soon as it is rolled out, and a later call with the
same states loads it instead of simulating again. :func:`studies.batch_verification.evaluate_many` keeps one
store per source beside its results (``<out>.rollouts/``) and removes it once the source's row is
written, so ``reach evaluate`` killed at any point (SIGKILL, Ctrl-C, the end of a session) loses
at most the block it was simulating.

Trust is checked, not assumed:

- one process owns a store at a time: it holds an exclusive lock on ``<store>/.lock`` from
  construction to :meth:`RolloutStore.close` (stores of one directory opened in the same process
  share it), so a second verification of the same source into the
  same ``--out`` is refused (:class:`~reach.locking.LockedError`) before it simulates or empties
  anything;
- the store's ``key`` (what was rolled out: the value function's fingerprint and the verification
  settings) is written as ``manifest.json``, and a store written under another key is emptied
  before use;
- every block records the digest of that key, the SHA-256 of its states, and a SHA-256 over the
  whole block (key, states, every outcome tensor and count). A block whose key, states, digest,
  shapes or dtypes do not match, or that cannot be read, is simulated again: a flipped bit in an
  outcome is caught. (The digests catch corruption and edits; someone able to rewrite the files
  and recompute the digests could equally rewrite the results table.)

Files are read with ``torch.load(weights_only=True)`` and written atomically.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import torch

from reach.atomic import atomic_path
from reach.locking import exclusive_lock
from reach.value_function import ValueFunction
from safety.verification.rollout import RolloutResult, RolloutSettings, concat_results, rollout

MANIFEST = "manifest.json"
#: per-state outcome tensors a block keeps, with their dtypes
OUTCOMES = {"collided": torch.bool, "collision_time": torch.float64, "decided_time": torch.float64}
#: ... and, for reach kinds, these too
REACH_OUTCOMES = {"reached": torch.bool, "reach_time": torch.float64}


def outcome_fields(kind: str) -> dict[str, torch.dtype]:
    """The per-state outcome tensors a block of a ``kind`` problem keeps, with their dtypes."""
    return {**OUTCOMES, **REACH_OUTCOMES} if kind != "avoid" else dict(OUTCOMES)


def states_digest(states: torch.Tensor) -> str:
    """SHA-256 of a block of states (shape, dtype and bytes): what the block's outcomes belong to."""
    x = states.detach().cpu().contiguous()
    head = f"{tuple(x.shape)}:{x.dtype}:".encode()
    return hashlib.sha256(head + x.numpy().tobytes()).hexdigest()


def key_digest(key: dict[str, Any]) -> str:
    """SHA-256 of a store key's canonical JSON: which store a block was written for."""
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


def block_digest(key: str, states: str, payload: dict[str, Any]) -> str:
    """SHA-256 over a whole block: its store key's and states' digests, each outcome tensor (dtype,
    shape, bytes) and its counts, so that any change to what the block says is detected."""
    h = hashlib.sha256(f"{key}:{states}:".encode())
    for name in ("initial_value", *outcome_fields(payload.get("kind", "avoid"))):
        t = payload[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    h.update(json.dumps([payload["state_steps"], payload["steps"], payload["wall_time"]]).encode())
    return h.hexdigest()


#: the store directories this process holds locked: lock and how many open stores share it. The lock
#: keeps other processes out; stores opened one after another in this process share it.
_HELD: dict[Path, tuple[contextlib.ExitStack, int]] = {}


def _acquire(directory: Path) -> None:
    key = directory.resolve()
    if key in _HELD:
        stack, count = _HELD[key]
        _HELD[key] = (stack, count + 1)
        return
    stack = contextlib.ExitStack()
    stack.enter_context(exclusive_lock(directory / ".lock", f"rollout store {directory}"))
    _HELD[key] = (stack, 1)


def _release(directory: Path) -> None:
    key = directory.resolve()
    stack, count = _HELD.pop(key, (None, 0))
    if count > 1:
        _HELD[key] = (stack, count - 1)
    elif stack is not None:
        stack.close()


class RolloutStore:
    """A directory of rolled-out blocks for one value function and one set of settings, owned by
    one process from construction to :meth:`close` (also a context manager)."""

    def __init__(self, directory: str | os.PathLike, key: dict[str, Any]) -> None:
        self.directory = Path(directory)
        self.key = json.loads(json.dumps(key, sort_keys=True, default=str))
        self.key_digest = key_digest(self.key)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._owned = False
        _acquire(self.directory)  # held until close(): one owning process, refused before any work
        self._owned = True
        manifest = self.directory / MANIFEST
        try:
            stored = json.loads(manifest.read_text())
        except (OSError, ValueError):
            stored = None
        if stored != self.key:  # another value function or settings (or none yet): start empty
            for block in self.directory.glob("*.pt"):
                block.unlink()
            with atomic_path(manifest) as tmp, open(tmp, "w") as fh:
                json.dump(self.key, fh, sort_keys=True)
        self.loaded_blocks = 0
        self.simulated_blocks = 0

    def close(self) -> None:
        """Release the store's lock (its blocks stay on disk for a later resume)."""
        if self._owned:
            self._owned = False
            _release(self.directory)

    def __enter__(self) -> RolloutStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_owned", False):
            self.close()

    def rollout(
        self,
        name: str,
        value_function: ValueFunction,
        states: torch.Tensor,
        settings: RolloutSettings | None = None,
        backend: Any = None,
        **run: Any,
    ) -> RolloutResult:
        """:func:`~safety.verification.rollout.rollout` of ``states`` in blocks of ``settings.chunk_size``,
        each loaded from the store if it holds that block of these states, else simulated and saved.
        The same outcomes as one call (the engine chunks the same way); ``wall_time`` and the work
        sum the blocks' own simulation, whenever it ran. A ``backend``
        (:class:`~safety.verification.sharding.RayBlocks`) simulates the missing blocks on its workers; this
        process alone writes the store."""
        if run.get("record"):
            raise ValueError("a RolloutStore keeps outcomes, not trajectories (record=True)")
        keywords = {k: run.pop(k) for k in list(run) if k in RolloutSettings.__dataclass_fields__}
        settings = RolloutSettings.of(settings, keywords)
        block = settings.chunk_size
        parts: list[RolloutResult | None] = []
        missing: list[tuple[int, torch.Tensor, Path, str]] = []
        for index, lo in enumerate(range(0, states.shape[0], block)):
            part = states[lo : lo + block]
            path = self.directory / f"{name}-{index:05d}.pt"
            digest = states_digest(part)
            result = self._load(path, digest, part.shape[0], value_function.system.kind)
            if result is None:
                missing.append((index, part, path, digest))
            else:
                self.loaded_blocks += 1
            parts.append(result)
        if not parts:
            return rollout(value_function, states, settings, **run)
        if backend is None:
            done = ((index, rollout(value_function, part, settings, **run)) for index, part, _, _ in missing)
        else:  # every missing block at once, on the backend's workers; each saved as it arrives
            arrived = backend.map(value_function, [part for _, part, _, _ in missing], settings, **run)
            done = ((missing[k][0], result) for k, result in arrived)
        where = {index: (path, digest) for index, _, path, digest in missing}
        for index, result in done:
            self._save(*where[index], result)
            self.simulated_blocks += 1
            parts[index] = result
        return concat_results(parts)

    def remove(self) -> None:
        """Delete the store (its results are in the table now) and release its lock."""
        shutil.rmtree(self.directory, ignore_errors=True)
        self.close()

    def _save(self, path: Path, digest: str, result: RolloutResult) -> None:
        payload = {
            "key": self.key_digest,
            "digest": digest,
            "kind": result.kind,
            "initial_value": result.initial_value,
            **{k: getattr(result, k) for k in outcome_fields(result.kind)},
            "state_steps": int(result.state_steps),
            "steps": int(result.steps),
            "wall_time": float(result.wall_time),
        }
        payload["block_digest"] = block_digest(self.key_digest, digest, payload)
        with atomic_path(path) as tmp:
            torch.save(payload, tmp)

    def _load(self, path: Path, digest: str, count: int, kind: str) -> RolloutResult | None:
        """The block at ``path`` if it is this store's, these states', whole and well formed, else
        None (simulate it)."""
        if not path.is_file():
            return None
        try:
            data = torch.load(path, map_location="cpu", weights_only=True)
        except Exception:  # an unreadable block is not trusted: it is simulated again
            return None
        if not isinstance(data, dict) or data.get("key") != self.key_digest or data.get("digest") != digest:
            return None
        if data.get("kind", "avoid") != kind:
            return None
        tensors = {"initial_value": None, **outcome_fields(kind)}
        for name, dtype in tensors.items():
            t = data.get(name)
            if not isinstance(t, torch.Tensor) or t.shape != (count,) or (dtype is not None and t.dtype != dtype):
                return None
        numbers = [data.get(k) for k in ("state_steps", "steps", "wall_time")]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in numbers):
            return None
        if data.get("block_digest") != block_digest(self.key_digest, digest, data):
            return None  # a changed outcome (a flipped bit, an edit) is simulated again, not trusted
        return RolloutResult(
            initial_value=data["initial_value"],
            **{k: data[k] for k in tensors if k != "initial_value"},
            state_steps=int(data["state_steps"]),
            steps=int(data["steps"]),
            wall_time=float(data["wall_time"]),
            kind=kind,
        )


__all__ = ["RolloutStore", "block_digest", "key_digest", "states_digest"]
