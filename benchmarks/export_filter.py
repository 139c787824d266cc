"""The exported safety filter against the torch filter: equal decisions, and what a decision costs.

Two studies, one command each (docs/results/export.md holds their tables):

    python benchmarks/export_filter.py equivalence --states 100000 [--engine native]
    python benchmarks/export_filter.py latency --calls 3000
    python benchmarks/export_filter.py graph
    python benchmarks/export_filter.py export-time air3d quadrotor [--no-onnx-optimizer]

For each system (Air3D's shipped network, the shipped 9D network, a user's system from
``examples/my_systems.py`` trained for a few hundred steps here) and each filter kind (each with its
default backup input, and the switch also with ``u*``, ``policy="gradient"``), the filter is
exported with :func:`safety.filters.export.export_filter` and run with :mod:`reach_runtime`.

``equivalence`` draws states uniformly from the domain, times-to-go uniformly over the horizon and
nominal inputs uniformly over the control box, and counts decisions that differ (and how many of
those lie within 1e-4 of the threshold), the largest value and gradient differences, and applied
inputs that differ where the decision agrees.

``graph`` counts operators: the ONNX nodes of each exported filter, and the ATen operations ``V``
alone and ``V`` with its gradient trace to (what a node costs at batch 1: docs/results/export.md).

``latency`` times one decision at batch 1 on one thread (``torch.set_num_threads(1)``, ONNX
Runtime with one intra-op thread), per call, the calls cycling through ``--states`` random states
(a decision's cost depends on the state: the switch computes its backup input only where it
intervenes): the torch filter, the runtime's ``Filter.__call__`` (its checks and the graph) and
the graph alone (``session.run``), then the same two for the native engine (``engine="native"``:
the graph compiled to C, :mod:`reach_runtime.native`) and its C function alone
(``NativeGraph.bound``: no copies, no checks), and the native call split by the decision (states
kept, states intervened on); then states per second at batch 1024. Run it on a quiet machine:
nothing else may run beside it.

``--engine native`` makes ``equivalence`` compare the native engine with the torch filter.

``export-time`` times ``export_filter("pretrained:NAME", ...)`` with its defaults, self-check
included, for each shipped model named, one after the other in one process (the first pays
torch's and ONNX's imports), and prints the file's size and the runtime's time per decision of 256
states (20 calls after one warm-up). ``--no-onnx-optimizer`` exports with torch's ONNX optimizer
off (``torch.onnx.export(..., optimize=False)``), to see what that pass costs and what it buys.
Run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))

from reach_runtime import Filter  # noqa: E402
from safety import SafetyFilter, load_value_function  # noqa: E402
from safety.filters.export import export_filter  # noqa: E402
from safety.filters.settings import FilterSettings  # noqa: E402

DT = 0.05
#: the filters of the study: each kind with its default backup input, and the switch backing up with u*
KINDS = ("switch", "switch-gradient", "smooth", "lookahead")


def filter_settings(kind: str, horizon: float) -> FilterSettings:
    """The settings of a study ``kind`` (``"switch-gradient"``: the switch with ``policy="gradient"``)."""
    if kind == "switch-gradient":
        return FilterSettings("switch", policy="gradient")
    return FilterSettings(kind, backup_horizon=horizon if kind == "lookahead" else None)


def user_system_network(folder: Path, steps: int) -> object:
    """A network of the docs' own-system example (DubinsAvoid), trained ``steps`` steps here (once:
    a run already in ``folder`` is reused)."""
    import my_systems  # noqa: F401  (registers the example systems)

    from training import TrainConfig, Trainer

    run = folder / f"user-{steps}"
    if not (run / "checkpoint.pt").exists():
        Trainer(TrainConfig(system="dubins-avoid", steps=steps, width=64), run, progress=False).train()
    return load_value_function(run).value_function


def sources(folder: Path, user_steps: int) -> dict[str, object]:
    return {
        "air3d": load_value_function("pretrained:air3d").value_function,
        "multivehicle9d": load_value_function("pretrained:multivehicle9d").value_function,
        "dubins-avoid (user)": user_system_network(folder, user_steps),
    }


def export_path(folder: Path, name: str, kind: str, horizon: float) -> Path:
    """Where the filter of system ``name`` and ``kind`` is exported (and found again)."""
    return folder / f"{name.split()[0]}-{kind}-{horizon:g}.onnx"


def exported(
    vf: object, name: str, kind: str, folder: Path, horizon: float, engine: str = "onnxruntime"
) -> tuple[dict, SafetyFilter, Filter, float | None]:
    """The filter exported to ``folder`` (reused when there: the time is then None), the torch filter
    of the same settings, and the runtime's filter."""
    settings = filter_settings(kind, horizon)
    path = export_path(folder, name, kind, horizon)
    seconds = None
    if not path.exists():
        start = time.perf_counter()
        export_filter(vf, path, settings, dt=DT, check_states=0)
        seconds = time.perf_counter() - start
    runtime = Filter.load(path, engine=engine)
    meta = runtime.metadata
    torch_filter = SafetyFilter(vf, meta.threshold, settings=FilterSettings(**meta.settings), dt=DT)
    return meta.raw, torch_filter, runtime, seconds


def filters(args: argparse.Namespace) -> Iterator[tuple[str, str, object, tuple]]:
    """Every (system, kind) of the study with its exported filter (:func:`exported`), in table order."""
    args.folder.mkdir(parents=True, exist_ok=True)
    for name, vf in sources(args.folder, args.user_steps).items():
        for kind in KINDS:
            yield name, kind, vf, exported(vf, name, kind, args.folder, args.horizon, args.engine)


def draws(system: object, count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = system.sample_states(count, generator=g)
    t = float(system.horizon) * torch.rand(count, generator=g)
    low = torch.tensor(system.control_bounds.low, dtype=torch.float32)
    high = torch.tensor(system.control_bounds.high, dtype=torch.float32)
    u = low + (high - low) * torch.rand(count, system.control_dim, generator=g)
    return x, t, u


def equivalence(args: argparse.Namespace) -> None:
    print(
        f"# equivalence: {args.states} states per system and kind, dt {DT}, lookahead backup {args.horizon} s, "
        f"engine {args.engine}"
    )
    print("| system | filter | export s | differ | near threshold | max dV | max dgrad | applied differ | max du |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, kind, vf, (meta, torch_filter, runtime, seconds) in filters(args):
        threshold = meta["threshold"]
        differ = near = applied_differ = 0
        dv = dg = du = 0.0
        for start in range(0, args.states, args.chunk):
            n = min(args.chunk, args.states - start)
            x, t, u = draws(vf.system, n, args.seed + start)
            applied, info = torch_filter(x, t, u)
            got, got_info = runtime(x.numpy(), u.numpy(), t.numpy())
            d = got_info.intervened != info.intervened.numpy()
            differ += int(d.sum())
            near += int((d & (np.abs(info.value.numpy() - threshold) < 1e-4)).sum())
            dv = max(dv, float(np.abs(got_info.value - info.value.numpy()).max()))
            dg = max(dg, float(np.abs(got_info.gradient - info.gradient.numpy()).max()))
            same = np.isclose(got, applied.numpy(), atol=1e-5).all(-1)
            applied_differ += int((~d & ~same).sum())
            du = max(du, float(np.abs(got - applied.numpy())[~d].max(initial=0.0)))
        took = "reused" if seconds is None else f"{seconds:.0f}"
        print(
            f"| {name} | {kind} | {took} | {differ} | {near} | {dv:.1e} | {dg:.1e} | {applied_differ} | {du:.1e} |",
            flush=True,
        )


def p50_p99(times: np.ndarray) -> tuple[float, float]:
    """The median and 99th percentile of call times (s) in microseconds; NaN for no calls."""
    if not len(times):
        return math.nan, math.nan
    return float(np.percentile(times, 50) * 1e6), float(np.percentile(times, 99) * 1e6)


def percentiles(fn: object, calls: int, states: int) -> tuple[float, float, np.ndarray]:
    """p50 and p99 (us) of ``fn(k)`` over ``calls`` calls cycling through ``states`` states (after a
    warm-up), and each call's time (s)."""
    for k in range(max(50, calls // 10)):
        fn(k % states)
    times = np.empty(calls)
    for i in range(calls):
        k = i % states
        start = time.perf_counter()
        fn(k)
        times[i] = time.perf_counter() - start
    return (*p50_p99(times), times)


def timings(
    system: object, torch_filter: SafetyFilter, runtime: Filter, native: Filter, args: argparse.Namespace
) -> tuple[list[tuple[float, float]], list[float]]:
    """Per-call percentiles at batch 1, cycling through ``args.states`` states (torch; ONNX Runtime:
    the runtime's call, the graph alone; the native engine: the same two, its C function alone,
    and its call split by the decision: the states where it keeps the nominal input, and where it
    intervenes) and states/s at batch 1024 (torch, ONNX Runtime, native)."""
    x, _, u = draws(system, 1024, args.seed)
    horizon = float(system.horizon)
    n = min(args.states, 1024)
    xs, us = x.numpy()[:n], u.numpy()[:n]
    rows = [(x[k : k + 1], u[k : k + 1]) for k in range(n)]
    feeds = [
        {"state": xs[k : k + 1], "time_to_go": np.array([horizon], np.float32), "u_nominal": us[k : k + 1]}
        for k in range(n)
    ]
    alone = [native._native.bound(feed) for feed in feeds]
    intervened = native(xs, us, horizon)[1].intervened
    row = [
        percentiles(lambda k: torch_filter(rows[k][0], horizon, rows[k][1]), args.calls, n),
        percentiles(lambda k: runtime(xs[k], us[k], horizon), args.calls, n),
        percentiles(lambda k: runtime.session.run(None, feeds[k]), args.calls, n),
        percentiles(lambda k: native(xs[k], us[k], horizon), args.calls, n),
        percentiles(lambda k: native._native.run(feeds[k]), args.calls, n),
        percentiles(lambda k: alone[k](), args.calls, n),
    ]
    calls = row[3][2]
    side = intervened[np.arange(args.calls) % n]
    split = [p50_p99(calls[~side]), p50_p99(calls[side])]
    rates = []
    for fn in (
        lambda: torch_filter(x, horizon, u),
        lambda: runtime(x.numpy(), u.numpy(), horizon),
        lambda: native(x.numpy(), u.numpy(), horizon),
    ):
        fn()
        start = time.perf_counter()
        for _ in range(10):
            fn()
        rates.append(10 * 1024 / (time.perf_counter() - start))
    return [(p50, p99) for p50, p99, _ in row] + split + [(100 * float(intervened.mean()), math.nan)], rates


def latency(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    print(f"# latency: batch 1, one thread, {args.calls} calls each cycling through {args.states} states "
          f"(p50 / p99 in microseconds); dt {DT}, lookahead backup {args.horizon} s; throughput at batch 1024 "
          "in states/s")  # fmt: skip
    print(
        "| system | filter | torch p50 / p99 | runtime p50 / p99 | graph p50 / p99 | native p50 / p99 "
        "| native graph p50 / p99 | C alone p50 / p99 | native, kept p50 / p99 | native, intervened p50 / p99 "
        "| intervened % | torch 1024 | runtime 1024 | native 1024 |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, kind, vf, (_, torch_filter, runtime, _) in filters(args):
        native = Filter.load(export_path(args.folder, name, kind, args.horizon), engine="native")  # built once, cached
        if args.prepare:
            continue
        row, rates = timings(vf.system, torch_filter, runtime, native, args)
        cells = " | ".join(f"{a:.0f} / {b:.0f}" for a, b in row[:-1])
        print(
            f"| {name} | {kind} | {cells} | {row[-1][0]:.1f} | {rates[0]:.0f} | {rates[1]:.0f} | {rates[2]:.0f} |",
            flush=True,
        )


def traced_operations(function: object, *example: torch.Tensor) -> int:
    """How many ATen operations ``function`` traces to (``make_fx``, symbolic batch), as the export does."""
    from torch.fx.experimental.proxy_tensor import make_fx

    def run(x: torch.Tensor, t: torch.Tensor) -> object:  # exactly two inputs, whatever ``function`` defaults
        return function(x, t)

    graph = make_fx(run, tracing_mode="symbolic", _allow_non_fake_inputs=True)(*example)
    return sum(node.op == "call_function" for node in graph.graph.nodes)


def graph(args: argparse.Namespace) -> None:
    """Operator counts: ONNX nodes of each exported filter, and the ATen operations that ``V`` alone
    and ``V`` with its gradient trace to. At batch 1 ONNX Runtime spends about a microsecond a node,
    so these counts bound what the traced path can reach."""
    import onnx

    from safety.filters.export import graph_value_function

    print("| system | V alone (ops) | V and grad V (ops) | switch (ONNX nodes) | switch, u* | smooth | lookahead |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, vf in sources(args.folder, args.user_steps).items():
        traced = graph_value_function(vf)
        x = vf.system.sample_states(4, generator=torch.Generator().manual_seed(args.seed))
        t = torch.full((4,), float(vf.system.horizon))
        alone = traced_operations(traced.value, x, t)
        with_gradient = traced_operations(traced.value_and_gradient, x, t)
        nodes = []
        for kind in KINDS:
            exported(vf, name, kind, args.folder, args.horizon)  # exports it where it is not yet
            nodes.append(len(onnx.load(export_path(args.folder, name, kind, args.horizon)).graph.node))
        print(f"| {name} | {alone} | {with_gradient} | {' | '.join(map(str, nodes))} |", flush=True)


def export_time(args: argparse.Namespace) -> None:
    """Wall time of each shipped model's export with its defaults, the file's size and the runtime's
    time per batch of 256 decisions."""
    import functools
    import tempfile

    if args.no_onnx_optimizer:  # the only way in: export_filter keeps torch's ONNX optimizer on
        torch.onnx.export = functools.partial(torch.onnx.export, optimize=False)
    print("| model | export (s) | file (MB) | runtime per 256 decisions (ms) |")
    print("|---|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as scratch:
        for name in args.names:
            start = time.perf_counter()
            result = export_filter(f"pretrained:{name}", Path(scratch) / f"{name}.onnx")
            seconds = time.perf_counter() - start
            runtime = Filter.load(result.path)
            meta = runtime.metadata
            low, high = np.array(meta.domain).T
            x = np.random.default_rng(args.seed).uniform(low, high, (256, meta.state_dim)).astype(np.float32)
            u = np.zeros((256, meta.control_dim), np.float32)
            t = 0.5 * sum(meta.time_range)
            runtime(x, u, t)
            start = time.perf_counter()
            for _ in range(20):
                runtime(x, u, t)
            per_call = (time.perf_counter() - start) / 20
            size = result.path.stat().st_size / 1e6
            print(f"| {name} | {seconds:.1f} | {size:.2f} | {1e3 * per_call:.2f} |", flush=True)


def main() -> None:
    warnings.filterwarnings("ignore")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="study", required=True)
    for name in ("equivalence", "latency", "graph"):
        p = sub.add_parser(name)
        p.add_argument("--horizon", type=float, default=0.25, help="the lookahead's backup horizon (s)")
        p.add_argument("--user-steps", type=int, default=300, help="training steps of the user system's network")
        p.add_argument("--seed", type=int, default=0)
        p.add_argument(
            "--folder", type=Path, default=ROOT / "runs" / "export_filter", help="exports kept here and reused"
        )
        p.set_defaults(engine="onnxruntime")
        if name == "equivalence":
            p.add_argument(
                "--engine",
                choices=("onnxruntime", "native"),
                default="onnxruntime",
                help="how the runtime runs the file",
            )
            p.add_argument("--states", type=int, default=100_000)
            p.add_argument("--chunk", type=int, default=10_000)
        else:
            p.add_argument("--calls", type=int, default=3000)
            p.add_argument("--states", type=int, default=1000, help="states the calls cycle through (at most 1024)")
            p.add_argument(
                "--prepare", action="store_true", help="export (or reuse) and compile the filters, time nothing"
            )
    p = sub.add_parser("export-time", help="time each shipped model's export with its defaults")
    from training.pretrained import card, names

    networks = [n for n in names() if card(n).format == "network"]
    p.add_argument(
        "names", nargs="+", choices=networks, metavar="NAME", help=f"shipped networks: {', '.join(networks)}"
    )
    p.add_argument("--no-onnx-optimizer", action="store_true", help="export with torch's ONNX optimizer off")
    p.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    studies = {"equivalence": equivalence, "latency": latency, "graph": graph, "export-time": export_time}
    studies[args.study](args)


if __name__ == "__main__":
    main()
