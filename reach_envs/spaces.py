"""What crosses an environment's boundary: its spaces, and the checks of actions, states and options.

Every environment kind (single, vector, PettingZoo) takes actions, initial states and ``reset``
options from a user, so one set of checks refuses what cannot be trusted - a wrong shape, NaN or
inf, a bool or a string given as a number, a misspelt option - with a ``ValueError`` naming it.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from gymnasium import spaces

from reach.systems.base import ControlAffineSystem
from reach.systems.box import Ball, InputSet


def observation_space(system: ControlAffineSystem) -> spaces.Box:
    """float32 states: periodic dimensions (headings) in [-pi, pi], the others unbounded (states may
    leave the sampling domain: cars drive off it, process noise is unbounded)."""
    low = np.array([-np.pi if p else -np.inf for p in system.periodic], dtype=np.float32)
    return spaces.Box(low=low, high=-low, dtype=np.float32)


def action_space(dim: int) -> spaces.Box:
    """Controls (turn rates, ...) normalised to [-1, 1]: -1 and 1 are the ends of each control's box
    (of a ball of controls' bounding box: :func:`inputs_of_actions` keeps them in the ball)."""
    return spaces.Box(low=-1.0, high=1.0, shape=(dim,), dtype=np.float32)


def inputs_of_actions(actions: np.ndarray, bounds: InputSet) -> np.ndarray:
    """Normalised actions ``(..., m)`` as inputs: each clipped to [-1, 1], then ``c + hw a``. For a
    ball of inputs (centre ``c``, radius ``r``) an action outside the unit ball is scaled back onto
    it, ``u = c + r a / max(1, |a|_2)``: the nearest input the system can take, as clipping is for a
    box (documented behaviour, like the clip)."""
    a = np.clip(np.asarray(actions, dtype=np.float64), -1.0, 1.0)
    if isinstance(bounds, Ball):
        a = a / np.maximum(1.0, np.linalg.norm(a, axis=-1, keepdims=True))
    return np.asarray(bounds.center) + np.asarray(bounds.half_width) * a


def check_action(action: object, shape: tuple[int, ...]) -> np.ndarray:
    """``action`` as float64 of the given shape; wrong shapes and NaN/inf raise ``ValueError``.

    Out-of-range values are *not* an error: callers clip them to [-1, 1] (documented behaviour,
    as for any Box action space whose samples an agent may overshoot).
    """
    try:
        raw = np.asarray(action)
    except (TypeError, ValueError) as err:
        raise ValueError(f"action must be numeric with shape {shape}, got {action!r}") from err
    if raw.dtype.kind not in "iuf":  # bools, strings ("0.5") and objects are not actions
        raise ValueError(f"action must hold real numbers with shape {shape}, got {action!r} ({raw.dtype})")
    a = raw.astype(np.float64)
    if a.shape != shape:
        raise ValueError(f"action must have shape {shape}, got shape {a.shape}: {action!r}")
    if not (all(map(math.isfinite, a.tolist())) if a.ndim == 1 and a.size <= 8 else np.isfinite(a).all()):
        raise ValueError(f"action contains a non-finite value (NaN or inf): {action!r}")
    return a


def check_reset_options(options: object, allowed: tuple[str, ...], unknown_keys: str = "raise") -> dict:
    """``reset`` options as a dict; unknown keys raise ``ValueError`` (a misspelt ``"sate"`` would
    otherwise start from a random state without a word), or with ``unknown_keys="warn"`` warn.

    The PettingZoo env warns instead of raising: PettingZoo's own API test resets with the made-up
    ``options={"options": 1}`` to check that ``options`` is accepted, and an env must pass that test."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise ValueError(f"reset options must be a dict, got {type(options).__name__}")
    unknown = sorted(map(str, set(options) - set(allowed)))
    if unknown:
        message = f"unknown reset option(s) {unknown}; this environment takes {list(allowed)}"
        if unknown_keys == "warn":
            warnings.warn(message + " (ignored)", UserWarning, stacklevel=3)
        else:
            raise ValueError(message)
    return options


class EpisodeOverError(RuntimeError):
    """``step`` was called before ``reset`` or after the episode ended (terminated or truncated)."""


def check_state(state: object, system: ControlAffineSystem) -> np.ndarray:
    """A user-given initial state as float64 ``(n,)``; wrong shapes and NaN/inf raise ``ValueError``."""
    raw = np.asarray(state)
    if raw.dtype.kind not in "iuf":
        raise ValueError(f"state for {system.name} must hold real numbers, got {state!r} ({raw.dtype})")
    x = raw.astype(np.float64)
    if x.shape != (system.state_dim,):
        raise ValueError(f"state for {system.name} must have shape ({system.state_dim},), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"state contains a non-finite value (NaN or inf): {x.tolist()}")
    return x
