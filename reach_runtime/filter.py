"""The torch-free safety filter: an exported ONNX graph behind the checks the torch filter makes.

See :mod:`reach_runtime`. The graph (``safety.filters.export``) is the torch filter's own decision, traced;
this module only checks inputs, runs the graph, and refuses what the graph flags. A file is used
only where its digest matches (:mod:`reach_runtime.digest`) and it passes the load checks
(:mod:`reach_runtime.load_checks`).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import onnxruntime

from reach_runtime.digest import read_model
from reach_runtime.load_checks import OUTPUTS, check_follows_metadata, check_interface, check_native, sampled_feeds
from reach_runtime.metadata import FilterMetadata, check_format

__all__ = ["ENGINES", "Filter", "FilterInfo"]

#: how a filter's graph can run (``Filter.load(..., engine=)``)
ENGINES = ("onnxruntime", "native")

_FLOAT32 = np.dtype(np.float32)
#: the dtypes one state may come in on the native engine's fast path (cast to float32 there)
_CASTS = (np.dtype(np.float32), np.dtype(np.float64))


@dataclass(frozen=True)
class FilterInfo:
    """What the filter saw and did, per state (leading batch shape as given; see ``safety.filters.base``)."""

    value: np.ndarray
    gradient: np.ndarray
    nominal: np.ndarray
    applied: np.ndarray
    intervened: np.ndarray
    infeasible: np.ndarray
    outside_domain: np.ndarray


class Filter:
    """An exported safety filter (see :mod:`reach_runtime`).

    ``Filter.load(path)`` opens the file; ``filter(x, u_nominal, t=None) -> (u, info)`` decides.
    ``threads`` (default 1: a control loop's filter should not compete for cores) sets ONNX
    Runtime's intra-op threads. ``engine="native"`` runs the graph compiled to C instead
    (:mod:`reach_runtime.native`: the same decision, a fraction of the latency at batch 1), behind
    the same checks.
    """

    def __init__(self, session: onnxruntime.InferenceSession, metadata: FilterMetadata, native: Any = None) -> None:
        self.session = session
        self.metadata = metadata
        self.engine = "onnxruntime" if native is None else "native"
        self._native = native
        self._outputs = [o.name for o in session.get_outputs()]
        # one state on the native engine: (state shape, control shape, times that need no second look)
        self._row_ok: tuple[tuple[int], tuple[int], tuple[float, float]] | None = None
        if native is not None and getattr(native, "_row", None) is not None:
            self._row_ok = ((metadata.state_dim,), (metadata.control_dim,), metadata.accepted_times())
            self._row_order = [native.output_names.index(name) for name in OUTPUTS]

    @classmethod
    def load(cls, path: str | os.PathLike, threads: int = 1, engine: str = "onnxruntime") -> Filter:
        """Open an exported filter; ``ValueError`` names a missing, unreadable, foreign or changed file.

        The file is read once: its digest (``reach.digest``, :mod:`reach_runtime.digest`) must match
        its contents, and the graph must be the filter's, with a free batch dimension and the widths
        its metadata declares, and follow its metadata on sampled states
        (:mod:`reach_runtime.load_checks`).

        ``engine``: ``"onnxruntime"`` (the default) runs the graph with ONNX Runtime; ``"native"``
        compiles it to C with the system's C compiler (once, cached; it needs the ``onnx`` package
        to read the graph) and calls that (``threads`` is then unused: the C code is one thread)."""
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
        where = os.fspath(path)
        if not os.path.isfile(where):
            raise ValueError(f"{where}: no such file (an exported filter is one .onnx file)")
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be a positive integer, got {threads!r}")
        model = read_model(where)
        check_format(model.metadata, where)
        digest = model.verify()  # before anything in the file is decoded or used
        metadata = FilterMetadata.from_properties(model.metadata, where)
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
        options.log_severity_level = 3
        try:  # the bytes whose digest was checked, not the file again
            session = onnxruntime.InferenceSession(model.data, options, providers=["CPUExecutionProvider"])
        except Exception as error:  # ONNX Runtime raises its own exception types for unreadable files
            raise ValueError(f"{where}: not a readable ONNX model ({type(error).__name__}: {error})") from None
        check_interface(session, metadata, where)
        feeds = sampled_feeds(metadata)
        expected = dict(zip([o.name for o in session.get_outputs()], session.run(None, feeds)))
        check_follows_metadata(feeds, expected, metadata, where)
        native = None
        if engine == "native":
            from reach_runtime.native import NativeGraph  # lazy: only this engine reads the graph (onnx) and compiles

            native = NativeGraph(where)
            if native.digest != digest:
                raise ValueError(f"{where}: the file changed while it was loaded (its digest differs between reads)")
            if native.input_names != ["state", "time_to_go", "u_nominal"]:
                raise ValueError(f"{where}: the compiled graph's inputs are {native.input_names}")
            check_native(feeds, expected, native, where)
        return cls(session, metadata, native)

    # ------------------------------------------------------------------ deciding
    def __call__(self, x: Any, u_nominal: Any, t: float | Any | None = None) -> tuple[np.ndarray, FilterInfo]:
        """Filtered inputs for states ``x`` ``(..., n)`` and nominal inputs ``(..., m)``.

        ``t`` is the time-to-go, a number or one per state; ``None`` takes the export's default
        (avoid's fixed horizon), and is refused where the time-to-go must count down. Returns the
        applied inputs (float32, the batch shape of ``x``) and a :class:`FilterInfo`. Raises
        ``ValueError`` for anything it cannot trust (see :mod:`reach_runtime`)."""
        if self._row_ok is not None and type(x) is np.ndarray and type(u_nominal) is np.ndarray:
            fast = self._one_state(x, u_nominal, t)
            if fast is not None:
                return fast
        return self._decide(x, u_nominal, t)

    def _one_state(self, x: np.ndarray, u: np.ndarray, t: Any) -> tuple[np.ndarray, FilterInfo] | None:
        """The control loop's call, one float32 or float64 state, on the native engine: its checks in
        C (the C file's ``reach_filter_checked``). None where the call is not of that form (then the
        general path decides). Where the C checks refuse, the general path is asked for the reason,
        so the error names the bad value as it always does; should it not refuse, the state is
        refused. A float64 beyond float32's range becomes inf in the cast, which the C checks refuse."""
        state_shape, control_shape, times = self._row_ok  # type: ignore[misc]
        if x.shape != state_shape or u.shape != control_shape:
            return None
        given_x, given_u = x, u  # the general path names a refused value as the caller gave it
        if x.dtype != _FLOAT32 or u.dtype != _FLOAT32:
            if x.dtype not in _CASTS or u.dtype not in _CASTS:
                return None
            with np.errstate(over="ignore"):
                x, u = x.astype(_FLOAT32), u.astype(_FLOAT32)
        else:
            u = u.copy()  # the info's nominal input: a copy, as the general path's
        if t is None:
            t = self.metadata.default_time_to_go
        if (type(t) is not float and type(t) is not int) or not times[0] <= t <= times[1]:
            return None
        status, out = self._native.checked_row(x, t, u)
        if status != 0:
            self._decide(given_x, given_u, t)
            raise ValueError(f"the compiled filter refused this state (status {status}); no nominal input is kept")
        control, value, gradient, intervened, infeasible, outside, _ = (out[k] for k in self._row_order)
        applied = control.reshape(control_shape)
        info = FilterInfo(
            value=value.reshape(()),
            gradient=gradient.reshape(state_shape),
            nominal=u,
            applied=applied,
            intervened=intervened.reshape(()),
            infeasible=infeasible.reshape(()),
            outside_domain=outside.reshape(()),
        )
        return applied, info

    def _decide(self, x: Any, u_nominal: Any, t: float | Any | None) -> tuple[np.ndarray, FilterInfo]:
        """Any batch shape and input type: NumPy's checks, then the graph (see :meth:`__call__`)."""
        meta = self.metadata
        xs = self._array(x, meta.state_dim, "states")
        batch = xs.shape[:-1]
        if xs.size == 0:
            raise ValueError(f"an empty batch of states (shape {xs.shape}): there is no state to decide")
        us = self._array(u_nominal, meta.control_dim, "u_nominal")
        if us.shape[:-1] != batch:
            raise ValueError(f"u_nominal must have shape {(*batch, meta.control_dim)}, got {us.shape}")
        ts = self._times(t, batch)
        flat = {
            "state": xs.reshape(-1, meta.state_dim),
            "time_to_go": ts.reshape(-1),
            "u_nominal": us.reshape(-1, meta.control_dim),
        }
        if self._native is not None:
            results = self._native.run(flat)
        else:
            try:
                results = self.session.run(None, flat)
            except Exception as error:  # ONNX Runtime's own types; the checks above should leave none
                raise ValueError(f"ONNX Runtime refused the inputs ({type(error).__name__}: {error})") from None
        out = dict(zip(self._outputs, results))
        if bool(np.asarray(out["untrusted"]).any()):
            raise ValueError(
                "the value function returned a non-finite value, gradient or optimal input in this batch; "
                "the filter does not trust it and keeps no nominal input"
            )
        applied = out["control"].reshape(*batch, meta.control_dim)
        info = FilterInfo(
            value=out["value"].reshape(batch),
            gradient=out["gradient"].reshape(*batch, meta.state_dim),
            nominal=us,
            applied=applied,
            intervened=out["intervened"].reshape(batch),
            infeasible=out["infeasible"].reshape(batch),
            outside_domain=out["outside_domain"].reshape(batch),
        )
        return applied, info

    @staticmethod
    def _array(values: Any, dim: int, what: str) -> np.ndarray:
        """``values`` as float32 ``(..., dim)``, refusing a wrong shape, a non-real dtype or NaN/inf
        (checked after the cast: a float64 of 1e300 overflows float32)."""
        array = np.asarray(values)
        if array.dtype.kind not in "fiu" or array.dtype.kind == "b":
            raise ValueError(f"{what} must be real numbers, got dtype {array.dtype}")
        if array.ndim == 0 or array.shape[-1] != dim:
            raise ValueError(f"{what} must have shape (..., {dim}), got {array.shape}")
        if array.dtype == np.float32:
            cast = array.copy()  # the common case, and the fast one: no cast can overflow
        else:
            with np.errstate(over="ignore"):
                cast = array.astype(np.float32)
        finite = np.isfinite(cast)
        if not finite.all():
            bad = array.reshape(-1, dim)[~finite.reshape(-1, dim).all(-1)][0].tolist()
            raise ValueError(f"{what} contain NaN or inf (or overflow float32), e.g. {bad}")
        return cast

    def _times(self, t: Any, batch: tuple[int, ...]) -> np.ndarray:
        """The time-to-go per state, refusing a missing one that must count down, a non-number, a
        wrong shape, and any time outside the range the value function covers."""
        meta = self.metadata
        if t is None:
            if meta.default_time_to_go is None:
                raise ValueError(
                    f"this {meta.problem} filter of {meta.system_name} needs the time-to-go t (it counts down "
                    "with the task's deadline)"
                )
            t = meta.default_time_to_go
        if isinstance(t, (str, bytes)):
            raise ValueError(f"t must be a time-to-go in seconds or an array of them, got {t!r}")
        low, high = meta.time_range
        first, last = meta.accepted_times()
        if type(t) is float or type(t) is int:  # one number (the common call at batch 1): checked without NumPy
            if type(t) is int and abs(t) > 2**1023:  # float(t) would overflow
                raise ValueError(f"time-to-go t is an integer of {t.bit_length()} bits: not a time-to-go in seconds")
            if not math.isfinite(t):
                raise ValueError(f"time-to-go t = {t} is not a finite number of seconds")
            if not first <= t <= last:
                raise ValueError(
                    f"time-to-go t = {float(t)} lies outside [{low:g}, {high:g}], the times this value function covers"
                )
            return np.full(batch, t, dtype=np.float32)
        times = np.asarray(t)
        if times.dtype.kind not in "fiu" or times.dtype.kind == "b":
            raise ValueError(f"t must be real numbers, got dtype {times.dtype}")
        if times.ndim and times.shape != batch and times.size != 1:
            raise ValueError(f"a per-state t must have shape {batch} (one per state), got {times.shape}")
        with np.errstate(over="ignore"):
            times = np.broadcast_to(times.astype(np.float64).reshape(() if times.size == 1 else batch), batch)
        if not np.isfinite(times).all():
            value = float(times[~np.isfinite(times)].reshape(-1)[0])
            raise ValueError(f"time-to-go t = {value} is not a finite number of seconds")
        bad = (times < first) | (times > last)
        if bad.any():
            value = float(times[bad].reshape(-1)[0])
            raise ValueError(
                f"time-to-go t = {value} lies outside [{low:g}, {high:g}], the times this value function covers"
            )
        return times.astype(np.float32)

    def __repr__(self) -> str:
        meta = self.metadata
        dt = "" if meta.dt is None or math.isnan(meta.dt) else f", dt={meta.dt:g}"
        return f"Filter({meta.kind} of {meta.system_name}, threshold={meta.threshold:g}{dt}, source={meta.source!r})"
