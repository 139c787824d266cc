"""The compiled library loaded with ``ctypes``: :class:`NativeGraph`, called like an ONNX Runtime
session.

The library is built or found in the cache by :func:`reach_runtime.native.build.build`, which
checks a cached library's size and SHA-256 against its record before it is handed here, so a
damaged file is rebuilt rather than loaded.
"""

from __future__ import annotations

import ctypes
import json
import os
import threading
from pathlib import Path
from typing import Any

import numpy as np

from reach_runtime.digest import DIGEST_KEY
from reach_runtime.native.build import build
from reach_runtime.native.emission import c_file, emitter_for

__all__ = ["NativeGraph"]


class NativeGraph:
    """The compiled decision, called like ``session.run``: ``graph.run(feeds) -> list of outputs``."""

    def __init__(self, path: str | os.PathLike, cache: str | os.PathLike | None = None) -> None:
        emitter = emitter_for(path)  # read and emitted once: the library is built from the same emitter
        stored = emitter.metadata.get(DIGEST_KEY)
        #: the digest of the file compiled (checked when read), or None for a graph that is no exported filter
        self.digest: str | None = None if stored is None else json.loads(stored)
        self._library_path = build(c_file(emitter, path, "reach_filter"), path, cache)
        try:
            self._lib = ctypes.CDLL(str(self._library_path))
        except OSError as error:  # checked against its record, so this is a library the loader refuses
            raise ValueError(f"{self._library_path}: the loader refused the compiled library ({error})") from None
        self._fn = self._lib.reach_filter
        self._fn.restype = ctypes.c_int
        self._inputs = [(t.name, t.value.dtype, t.value.shape[1:]) for t in emitter.inputs]
        self._outputs = [(t.name, t.value.dtype, t.value.shape) for t in emitter.outputs]
        self._lock = threading.Lock()  # the generated code's buffers are static: one call at a time
        self._slots: dict[int, tuple[list[np.ndarray], list[np.ndarray], list[Any]]] = {}
        self.input_names = [name for name, _, _ in self._inputs]
        self.output_names = [name for name, _, _ in self._outputs]
        # the C file's checked entry (a reach filter's graph only): one state, checks and all, in C
        checked = getattr(self._lib, "reach_filter_checked", None)
        self._row = None if checked is None else (checked, *self._allocate(1))

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """The outputs for ``feeds`` (arrays with a leading batch axis), in the graph's order.

        The C function reads and writes buffers kept per batch size (their addresses are resolved
        once: at batch 1 that lookup would cost more than the decision); the inputs are copied in
        and the outputs copied out, so no call's results share memory with another's."""
        arrays = [feeds[name] for name in self.input_names]
        n = int(np.shape(arrays[0])[0]) if np.ndim(arrays[0]) else 0
        with self._lock:  # the generated code's buffers are static, and so are these
            slots = self._slots.get(n)
            if slots is None:
                slots = self._slots[n] = self._allocate(n)
                if len(self._slots) > 8:
                    self._slots.pop(next(iter(self._slots)))
            ins, outs, args = slots
            for slot, array, (name, _, _) in zip(ins, arrays, self._inputs):
                if np.shape(array) != slot.shape:
                    raise ValueError(f"{name} must have shape {slot.shape}, got {np.shape(array)}")
                np.copyto(slot, array, casting="same_kind")
            status = self._fn(*args)
            results = [o.copy() for o in outs]
        if status != 0:
            raise ValueError("the compiled filter met an index outside its tensor; the decision is not trusted")
        return results

    def checked_row(self, state: np.ndarray, time_to_go: float, u_nominal: np.ndarray) -> tuple[int, list[np.ndarray]]:
        """One state through the C file's checked entry (``reach_filter_checked``): the status
        (:data:`~reach_runtime.native.emission.STATUS`; nonzero: the decision must not be used, and the outputs are then
        meaningless) and copies of the outputs, each ``(1, ...)`` or a flag. ``state`` and
        ``u_nominal`` are float32 rows of the graph's widths (not checked here: the caller's fast
        path has). The per-call cost of :meth:`run` less its dictionary, shape checks and NumPy
        checks of finiteness, which the C entry makes."""
        if self._row is None:
            raise ValueError("this graph has no checked entry (it is not an exported reach filter)")
        function, ins, outs, args = self._row
        with self._lock:
            ins[0][0] = state
            ins[1][0] = time_to_go
            ins[2][0] = u_nominal
            status = function(*args)
            return status, [o.copy() for o in outs]

    def bound(self, feeds: dict[str, np.ndarray]) -> Any:
        """A call of the C function alone on ``feeds``, without arguments (to time the compiled
        code apart from the copies and checks around it). Its outputs are discarded."""
        arrays = [np.asarray(feeds[name]) for name in self.input_names]
        ins, outs, args = self._allocate(int(arrays[0].shape[0]))
        for slot, array in zip(ins, arrays):
            np.copyto(slot, array, casting="same_kind")
        function = self._fn

        def call(_buffers: tuple = (ins, outs)) -> int:  # held: the arguments point into these buffers
            return function(*args)

        return call

    def _allocate(self, n: int) -> tuple[list[np.ndarray], list[np.ndarray], list[Any]]:
        ins = [np.zeros((n, *row), dtype) for _, dtype, row in self._inputs]
        outs = [np.zeros((n, *shape[1:]) if shape else (), dtype) for _, dtype, shape in self._outputs]
        args = [ctypes.c_long(n), *(ctypes.c_void_p(a.ctypes.data) for a in (*ins, *outs))]
        return ins, outs, args

    @property
    def library(self) -> Path:
        """The shared library this graph runs."""
        return self._library_path
