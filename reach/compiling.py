"""``torch.compile`` where it works, eager mode where it does not, one rule for the whole package.

``torch.compile`` fuses chains of elementwise operations into single kernels (the grid solver's
right-hand side, a training step's sine layers and their derivatives), but on CPU it needs a working
C++ compiler, and a failure shows only on the first call. :func:`maybe_compile` wraps a function so
that the first call compiles it and, if that fails, warns once and stays in eager mode, unless the
caller insisted on compiling.
"""

from __future__ import annotations

import types
import warnings
from collections.abc import Callable
from typing import Any

import torch


def maybe_compile(
    fn: Callable[..., Any], compile: bool | None, what: str = "running", own_cache: bool = False
) -> Callable[..., Any]:
    """``fn`` compiled by ``torch.compile`` (``compile`` True or None) or as it is (False).

    ``None`` falls back to eager mode with a warning when compiling fails; ``True`` raises instead.
    ``what`` names the job in the warning (``"training in eager mode"``). Shapes are compiled static:
    pass changing scalars as tensors so that they do not trigger recompiles. ``own_cache`` compiles
    a private copy of ``fn``'s code (see :func:`_own_code`): for closures over an object that differs
    from call to call (a network), whose compiled graphs no later call can reuse. Without it, calls
    that close over equal things (the grid solver's step on the same grid) share compiled code.
    """
    if compile is False:
        return fn
    try:
        compiled = torch.compile(_own_code(fn) if own_cache else fn, dynamic=False)
    except Exception:  # pragma: no cover - torch without a working compiler stack
        if compile:
            raise
        return fn
    state = {"fn": compiled, "tried": False}

    def run(*args: Any, **kwargs: Any) -> Any:
        if state["tried"]:
            return state["fn"](*args, **kwargs)
        try:
            out = state["fn"](*args, **kwargs)
        except Exception as err:
            if compile:
                raise
            warnings.warn(f"torch.compile failed ({type(err).__name__}: {err}); {what} in eager mode", stacklevel=2)
            state["fn"] = fn  # e.g. no working C++ compiler: stay in eager mode
            out = fn(*args, **kwargs)
        state["tried"] = True
        return out

    return run


def _own_code(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with a private copy of its code object.

    Dynamo keeps its compiled graphs, and counts recompilations, per *code object*. Every call of a
    factory such as :func:`training.loss.residual_function` makes a closure over the same code, so a
    process that compiles it for a ninth network (a sweep worker running its ninth run) finds eight
    stale entries whose guards fail, hits ``torch._dynamo.config.recompile_limit`` (8) and silently
    runs that network in eager mode, which is slower (measured: docs/results/training.md, *Training
    throughput*). A private copy gives each wrapper its own
    cache and count, which are dropped with the wrapper.
    """
    if not isinstance(fn, types.FunctionType):
        return fn
    copy = types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    copy.__kwdefaults__ = fn.__kwdefaults__
    copy.__dict__.update(fn.__dict__)
    copy.__qualname__ = fn.__qualname__
    return copy
