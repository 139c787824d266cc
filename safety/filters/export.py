"""Export a safety filter to one ONNX graph that runs without torch (:mod:`reach_runtime`).

``export_filter(source, "f.onnx", FilterSettings(kind="switch"), dt=0.05)`` writes a single ONNX
file: the filter's whole decision for a batch of states, time-to-go and nominal inputs, with the
value, its gradient and the decision's flags as outputs, and in its metadata everything the runtime
needs to check its inputs and everything a reader needs to know what it holds (the system and its
parameters, the settings in force, ``dt`` and the integrator, the source and its fingerprint, and
whether the source passed its trust bar: :func:`source_verdict`). Each fact is stored once (the
threshold is the settings'), and the file is sealed with the SHA-256 of everything in it
(``reach.digest``, :mod:`reach_runtime.digest`): the runtime refuses a file changed after export.

**One implementation.** The graph is not a second filter written for ONNX: it is
:meth:`safety.filters.base.SafetyFilter.decide` itself, traced by ``make_fx`` into ATen operations
(autograd of the margins included) and converted by torch's ONNX exporter. While it is traced,
checks that would raise record into an ``untrusted`` output instead, and value-dependent shortcuts
compute every row (:mod:`safety.tracing`): the traced decision is the eager one.

**What is checked where.** The runtime checks shapes, NaN and inf, and the time-to-go's range
before it runs the graph, as :meth:`SafetyFilter.__call__` does; the graph flags non-finite values,
gradients and optimal inputs (``untrusted``: the runtime raises) and states outside the domain
(``outside_domain``: the filter intervenes, :class:`~safety.filters.settings.FilterSettings`).

**Refused**, naming what: a value function that is not a network or a minimum of networks (a grid's
interpolation is not traced), a network multiplying in reduced precision, an output path that is not
a writable ``.onnx`` file, a default time-to-go outside the times the value function covers, and
every setting :class:`SafetyFilter` refuses. The decision is traced at a batch size that is no
input's width (:func:`example_batch`), and a converted graph without one free batch dimension is
refused. After writing, the file is loaded as the runtime loads it, run with ONNX Runtime on sampled
states and compared with the eager filter; an export whose decisions differ away from the threshold
is removed and refused.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from reach.atomic import atomic_path
from reach.systems.base import ControlAffineSystem
from reach.systems.box import Ball
from reach.validation import check_output_path
from reach.value_function import MinimumOf, ValueFunction, time_range
from safety.filters.base import SafetyFilter
from safety.filters.settings import REMAINING, FilterSettings, make_filter_settings, settings_for_system
from safety.tracing import recording_trust
from safety.value_loading import as_value_function
from training.checkpoint import network_digest
from training.network import NeuralValueFunction
from training.pretrained import PREFIX, card, is_pretrained

__all__ = [
    "INPUTS",
    "OUTPUTS",
    "ExportedFilter",
    "example_batch",
    "export_filter",
    "graph_value_function",
    "source_verdict",
]

#: the graph's inputs: states ``(B, n)``, times-to-go ``(B,)`` and nominal inputs ``(B, m_u)``, float32
INPUTS = ("state", "time_to_go", "u_nominal")

#: the graph's outputs, per state: the applied input, ``V``, ``grad V``, whether the filter overrode
#: the nominal input, whether the smooth filter found no feasible input, whether the state lay
#: outside the domain; and one flag for the batch: whether any value it read was non-finite
OUTPUTS = ("control", "value", "gradient", "intervened", "infeasible", "outside_domain", "untrusted")

#: operations with no ONNX conversion of their own, written as ones that have one
_DECOMPOSITIONS = {
    torch.ops.aten.hypot.default: lambda a, b: torch.sqrt(a * a + b * b),
    torch.ops.prims.hypot.default: lambda a, b: torch.sqrt(a * a + b * b),
}

#: states sampled to check an export against the eager filter before it is kept
CHECK_STATES = 512


@dataclass(frozen=True)
class ExportedFilter:
    """What :func:`export_filter` wrote: the file, its metadata (as stored, JSON-decoded) and the
    self-check's count of decisions that differ from the eager filter (all within the threshold's
    float32 rounding, else the export is refused)."""

    path: Path
    metadata: dict[str, Any]
    checked: int
    differing: int


def graph_value_function(vf: ValueFunction) -> ValueFunction:
    """``vf`` as a graph trace can run it, or ``ValueError`` naming why it cannot be exported.

    A network becomes :meth:`~training.network.NeuralValueFunction.unchecked` (the runtime makes
    its checks); a :class:`~reach.value_function.MinimumOf` networks keeps its members' order,
    labels and steering. Grid solutions (interpolation tables, :mod:`groundtruth`) are refused."""
    if isinstance(vf, NeuralValueFunction):
        if vf.matmul_dtype is not None:
            raise ValueError(
                f"a value network multiplying in {vf.matmul_dtype} cannot be exported; export it in float32"
            )
        return vf.unchecked()
    if isinstance(vf, MinimumOf):
        members = [graph_value_function(m) for m in vf.members]
        return MinimumOf(*members, labels=vf.labels, steer_by=vf.steer_by)
    raise ValueError(
        f"a {type(vf).__name__} cannot be exported to ONNX: only value networks and minimums of them "
        "(min:A,B of networks) are; a grid's interpolation is not traced"
    )


def _fingerprint(vf: ValueFunction) -> str:
    """The source's fingerprint: each network's checkpoint digest (``+`` between a minimum's members)."""
    if isinstance(vf, NeuralValueFunction):
        return "sha256:" + network_digest(vf.network)
    assert isinstance(vf, MinimumOf)  # graph_value_function refused anything else
    return "+".join(_fingerprint(m) for m in vf.members)


def _input_set(bounds: Any) -> dict[str, Any]:
    if isinstance(bounds, Ball):
        return {"ball": {"center": list(bounds.center), "radius": float(bounds.radius)}}
    return {"box": {"low": list(bounds.low), "high": list(bounds.high)}}


def _default_time_to_go(settings: FilterSettings, system: ControlAffineSystem) -> float | None:
    """The time-to-go the runtime uses when its caller gives none: avoid's fixed horizon (or the
    settings' number); None where it must count down (``"remaining"``, every reach kind)."""
    if system.problem.reaches or settings.time_to_go == REMAINING:
        return None
    return float(system.horizon if settings.time_to_go is None else settings.time_to_go)


def _metadata(
    vf: ValueFunction,
    filt: SafetyFilter,
    settings: FilterSettings,
    dt: float | None,
    integrator: str,
    label: str,
) -> dict[str, Any]:
    from reach_runtime.metadata import FORMAT  # lazy: the runtime's package loads ONNX Runtime (the export extra)

    system = filt.system
    low, high = time_range(vf) or (0.0, float(system.horizon))
    return {
        "format": FORMAT,
        "system": system.config(),
        "system_name": system.name,
        "problem": system.kind,
        "state_dim": system.state_dim,
        "control_dim": system.control_dim,
        "domain": [list(map(float, d)) for d in system.domain],
        "wrapped_dims": list(system.periodic_dims),
        "control_set": _input_set(system.control_bounds),
        "settings": {**filt.settings.keywords(), "policy": settings.backup_policy},
        "dt": dt,
        "integrator": integrator,
        "time_range": [float(low), float(high)],
        "default_time_to_go": _default_time_to_go(settings, system),
        "backup_steps": filt.backup_steps,
        "inputs": list(INPUTS),
        "outputs": list(OUTPUTS),
        "source": label,
        "fingerprint": _fingerprint(vf),
        "source_verdict": source_verdict(label),
        "torch": torch.__version__,
    }


def source_verdict(source: str) -> dict[str, Any]:
    """Whether the exported source passed its trust bar, as the file records it: for
    ``pretrained:NAME``, its model card's verdict (``passes`` and its line); for any other source,
    the user's own value function, which carries no verdict (``passes`` None)."""
    if is_pretrained(source):
        verdict = card(source[len(PREFIX) :]).verdict
        return {"passes": bool(verdict.passes), "line": f"{source} {verdict.line()}"}
    return {"passes": None, "line": f"{source}: the user's own value function, no trust verdict (yours to judge)"}


def _check_default_time(metadata: dict[str, Any]) -> None:
    """Refuse a default time-to-go (``time_to_go=T``, or the horizon) outside the times the value
    function covers: the runtime would refuse every call that relies on it."""
    default, (low, high) = metadata["default_time_to_go"], metadata["time_range"]
    if default is not None and not low <= default <= high:
        raise ValueError(
            f"time-to-go {default:g} lies outside [{low:g}, {high:g}], the times the value function covers; "
            "give a time-to-go in that range, or 'remaining' (the caller passes it)"
        )


def _check_free_batch(model: Any) -> None:
    """Refuse a converted graph whose inputs or outputs do not all share one free batch dimension."""
    names = []
    for value in [*model.graph.input, *model.graph.output]:
        if value.name not in INPUTS + OUTPUTS[:-1]:
            continue
        dims = value.type.tensor_type.shape.dim
        names.append(dims[0].dim_param if dims and dims[0].HasField("dim_param") else None)
    if None in names or len(set(names)) != 1:
        raise ValueError(
            "the converted graph does not keep one free batch dimension for its inputs and outputs "
            f"(leading dimensions: {names}); this is a bug of the export"
        )


def _decision(filt: SafetyFilter) -> Any:
    """The function the graph is traced from: the filter's decision and its flags, as :data:`OUTPUTS`."""

    def decision(x: torch.Tensor, t: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, ...]:
        # one batch size for the three inputs (else the trace may fix one of them to the example's)
        torch._check(t.shape[0] == x.shape[0])
        torch._check(u.shape[0] == x.shape[0])
        with recording_trust() as ledger:
            applied, info = filt.decide(x, t, u)
            untrusted = ledger.flag(x)
        infeasible = info.infeasible if info.infeasible is not None else torch.zeros_like(info.intervened)
        assert info.gradient is not None and info.outside_domain is not None
        return applied, info.value, info.gradient, info.intervened, infeasible, info.outside_domain, untrusted

    return decision


def _example(filt: SafetyFilter, batch: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """States sampled from the domain, times-to-go over the covered range, nominal inputs in the set."""
    system = filt.system
    generator = torch.Generator().manual_seed(0)
    x = system.sample_states(batch, generator=generator)
    low, high = time_range(filt.value_function) or (0.0, float(system.horizon))
    t = low + (high - low) * torch.rand(batch, generator=generator)
    centre = torch.tensor(system.control_bounds.center, dtype=torch.float32)
    half = (
        torch.full_like(centre, float(system.control_bounds.radius))
        if isinstance(system.control_bounds, Ball)
        else torch.tensor(system.control_bounds.high, dtype=torch.float32) - centre
    )
    u = centre + half * (2 * torch.rand(batch, system.control_dim, generator=generator) - 1)
    return x, t, u


def example_batch(system: ControlAffineSystem) -> int:
    """The batch size the decision is traced at: 4, or the next size that is no input's width.

    A symbolic trace gives equal sizes of its inputs one symbol; a batch equal to the state or
    input width would then be tied to it, and the first operation that fixes the width fixes the
    batch too (a 4-input system traced at batch 4 exported a graph for batches of 4 only)."""
    batch = 4
    while batch in (system.state_dim, system.control_dim):
        batch += 1
    return batch


#: what the export's progress bar names at each stage; the conversion takes nearly all of the time
#: (torch's ONNX exporter: 10 s to 12 minutes on 2 cores for the shipped networks, docs/results/benchmarks.md)
EXPORT_STAGES = (
    "tracing the filter",
    "converting to ONNX (torch's exporter: seconds to minutes)",
    "checking the file against the torch filter",
)


def _trace(filt: SafetyFilter) -> tuple[Any, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """The decision traced with symbolic batch size into ATen operations, and the example it saw."""
    from torch.fx.experimental.proxy_tensor import make_fx  # lazy: tracing machinery, export only

    example = _example(filt, example_batch(filt.system))
    graph = make_fx(
        _decision(filt), tracing_mode="symbolic", decomposition_table=_DECOMPOSITIONS, _allow_non_fake_inputs=True
    )(*example)
    graph.eval()  # a traced graph starts in training mode, which the exporter warns of (it has no such layers)
    return graph, example


def _convert(graph: Any, example: tuple[torch.Tensor, torch.Tensor, torch.Tensor], path: str) -> None:
    """Write the traced decision ``graph`` as ONNX to ``path``, its batch dimension free."""
    batch = torch.export.Dim("batch")
    torch.onnx.export(
        graph,
        example,
        path,
        dynamo=True,
        input_names=list(INPUTS),
        output_names=list(OUTPUTS),
        dynamic_shapes=({0: batch}, {0: batch}, {0: batch}),
        external_data=False,
        verbose=False,
    )


def _self_check(filt: SafetyFilter, path: Path, states: int) -> tuple[int, int]:
    """Load the written file with the runtime (:meth:`reach_runtime.Filter.load`: its checks), run
    it with ONNX Runtime on sampled inputs and compare with the eager filter: ``(checked,
    differing)``; raises where the runtime refuses the file or a decision differs away from the
    threshold."""
    import numpy as np  # lazy: the self-check only

    from reach_runtime import Filter  # lazy: loads ONNX Runtime, an optional dependency (the export extra)

    x, t, u = _example(filt, states)
    # loaded as a robot loads it: its digest, its interface, and its graph following its metadata checked
    session = Filter.load(path).session
    out = dict(zip(OUTPUTS, session.run(None, {"state": x.numpy(), "time_to_go": t.numpy(), "u_nominal": u.numpy()})))
    if bool(out["untrusted"]):
        raise ValueError(f"the exported filter flags untrusted values on states sampled from the domain ({path})")
    _, info = filt(x, t, u)
    differ = out["intervened"] != info.intervened.numpy()
    near = np.abs(filt.problem.orient(torch.from_numpy(out["value"])).numpy() - filt.threshold) < 1e-4
    if bool((differ & ~near).any()) and filt.kind != "lookahead":
        raise ValueError(f"the exported filter decides differently from the eager one on {int(differ.sum())} states")
    return states, int(differ.sum())


def export_filter(
    source: ValueFunction | str | os.PathLike,
    out: str | os.PathLike,
    settings: FilterSettings | None = None,
    *,
    dt: float | None = None,
    integrator: str = "rk4",
    system: ControlAffineSystem | None = None,
    check_states: int = CHECK_STATES,
    progress: bool = True,
    **options: Any,
) -> ExportedFilter:
    """Write the safety filter of ``source`` with ``settings`` to the ONNX file ``out``.

    Args:
        source: a value function, or where to load one (a run, a ``.pt`` file, ``pretrained:NAME``,
            ``min:A,B``; :func:`~safety.value_loading.as_value_function`).
        out: the ``.onnx`` file to write (atomically; its folder is created).
        settings: the filter's :class:`FilterSettings`, or field by field in ``options``. An unset
            threshold takes the env adapters' rule for a filter acting every ``dt``
            (:meth:`FilterSettings.threshold_for`; 0 without ``dt``).
        dt: the control period (required for the lookahead; sets the default threshold).
        integrator: how the lookahead and the greedy backup predict (``"rk4"`` or ``"euler"``).
        system: the system the filter serves (default: the value function's).
        check_states: states sampled for the self-check against the eager filter (0: none).
        progress: show a progress bar over the export's stages (:data:`EXPORT_STAGES`), with the
            time spent; the conversion can take minutes for a large network.

    Everything is checked before the trace (the output path, the value function, the settings).
    Returns an :class:`ExportedFilter`.
    """
    out_path = check_output_path(out, "exported filter")
    if out_path.suffix != ".onnx":
        raise ValueError(f"exported filter path {str(out_path)!r} must end in .onnx")
    vf = as_value_function(source)
    graph_vf = graph_value_function(vf)
    settings = make_filter_settings(settings, **options)
    served = system if system is not None else vf.system
    settings = settings_for_system(settings, served)
    threshold = settings.threshold_for(served, dt) if dt is not None else settings.threshold_for(served)
    filt = SafetyFilter(graph_vf, threshold, settings=settings, dt=dt, integrator=integrator, system=system)
    label = str(source) if isinstance(source, (str, os.PathLike)) else type(vf).__name__
    metadata = _metadata(vf, filt, settings, dt, integrator, label)
    _check_default_time(metadata)
    import onnx  # lazy: an optional dependency (the export extra)

    from reach_runtime.digest import seal  # lazy: the runtime's package loads ONNX Runtime (the export extra)

    stages = EXPORT_STAGES if check_states else EXPORT_STAGES[:-1]
    with (
        tqdm(  # stages of very different lengths: the time spent, no rate or estimate
            total=len(stages),
            desc="export",
            bar_format="{desc} [{elapsed}, {n_fmt} of {total_fmt} stages done]",
            **({} if progress else {"disable": True}),
        ) as bar,
        tempfile.TemporaryDirectory() as scratch,
    ):
        bar.set_description_str(f"export: {stages[0]}")
        graph, example = _trace(filt)
        bar.update(1)
        bar.set_description_str(f"export: {stages[1]}")
        raw = os.path.join(scratch, "graph.onnx")
        _convert(graph, example, raw)
        model = onnx.load(raw)
        bar.update(1)
        _check_free_batch(model)
        for key, value in metadata.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = f"reach.{key}", json.dumps(value)
        model.doc_string = f"reach safety filter ({settings.kind}) of {metadata['system_name']} from {label}"
        with atomic_path(out_path) as tmp:
            Path(tmp).write_bytes(seal(model.SerializeToString(), str(out_path)))
        checked, differing = 0, 0
        if check_states:
            bar.set_description_str(f"export: {stages[2]}")
            try:
                checked, differing = _self_check(filt, out_path, check_states)
            except BaseException:
                out_path.unlink(missing_ok=True)
                raise
            bar.update(1)
    return ExportedFilter(out_path, metadata, checked, differing)
