"""The 9D default training step on a GPU: eager against one CUDA graph, steps/s and the loss curve.

Usage (on a CUDA machine): ``python benchmarks/gpu_step.py [--steps 1500] [--points 65536 8192]
[--variants eager,graph,...]``

Each variant trains the 9D default recipe (``reach train --system multivehicle9d``, the schedule run
over ``--steps`` steps) from seed 0 in a fresh run directory, in this one process, one variant after
the other (nothing else on the GPU). Reported per variant:

* ``warm-up s``: the first 100 steps' wall time (compilation, capture, allocator);
* ``steps/s``: the steps after the first 100 over their wall time (each step reads its loss terms
  back, as every training step does, so the clock sees the GPU's work);
* the loss curve against the eager run of the same points (same seed, same draws): the largest
  relative difference of any step's loss, and the mean loss of the last 10 % of steps.

Variants: ``eager`` and ``graph`` (the step as one CUDA graph, :mod:`training.cuda_graph`), each
``-nocompile`` (the fused residual eager) or compiled (the default for runs of 2,000 steps and more,
forced on here); ``graph-tf32`` also lets the GPU's TF32 units do float32 matrix products
(``--tf32``). ``--profile`` adds what torch.profiler sees in 20 more steps of each.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from training.config import TrainConfig
from training.trainer import Trainer, matmul_precision

VARIANTS = {
    "eager": {"cuda_graph": False, "compile": True},
    "eager-nocompile": {"cuda_graph": False, "compile": False},
    "graph": {"cuda_graph": True, "compile": True},
    "graph-nocompile": {"cuda_graph": True, "compile": False},
    "graph-tf32": {"cuda_graph": True, "compile": True, "matmul_precision": "tf32"},
}
WARMUP = 100


def kernels_per_step(trainer: Trainer, points: int, variant: str, steps: int = 20) -> None:
    """What the GPU does in one step: torch.profiler over ``steps`` more steps, the kernels' summed time
    per step (against the step's wall time) and the kernels that take most of it."""
    from torch.profiler import ProfilerActivity, profile  # lazy: only with --profile

    torch.cuda.synchronize()
    start = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            trainer._optimise()
        torch.cuda.synchronize()
    wall = (time.perf_counter() - start) / steps * 1e3
    events = [e for e in prof.key_averages() if e.device_type.name == "CUDA" or e.self_device_time_total > 0]
    device_ms = sum(e.self_device_time_total for e in events) / steps / 1e3
    launches = sum(e.count for e in events) / steps
    print(
        f"# profile {variant} {points}: {wall:.2f} ms/step wall (profiled), kernels {device_ms:.2f} ms/step, "
        f"{launches:.0f} kernels/step"
    )
    for e in sorted(events, key=lambda e: -e.self_device_time_total)[:12]:
        print(f"#   {e.self_device_time_total / steps / 1e3:7.3f} ms  x{e.count / steps:5.1f}  {e.key[:110]}")


def train(
    points: int, steps: int, variant: str, workdir: Path, device: str, profile: bool = False
) -> tuple[float, float, list[float]]:
    """``(warm-up s, steps/s after it, per-step losses)`` of one variant."""
    options = VARIANTS[variant]
    config = TrainConfig(
        system="multivehicle9d",
        points=points,
        steps=steps,
        seed=0,
        device=device,
        log_every=10**9,
        checkpoint_every_s=10**9,
        **options,
    )
    trainer = Trainer(config, workdir / f"{variant}-{points}", progress=False)
    losses = []
    start = time.perf_counter()
    sync = torch.cuda.synchronize if device.startswith("cuda") else lambda: None
    with matmul_precision(config.matmul_precision):  # what Trainer.train applies
        for i in range(steps):
            if i == WARMUP:
                sync()
                warm = time.perf_counter()
            losses.append(trainer._optimise().terms["loss"])
        sync()
        end = time.perf_counter()
        if profile:
            kernels_per_step(trainer, points, variant)
    if options["cuda_graph"] and not (trainer.graphed and trainer.graphed.captured):
        raise RuntimeError(f"{variant}: the step was not captured")
    return warm - start, (steps - WARMUP) / (end - warm), losses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--points", type=int, nargs="+", default=[65536, 8192])
    parser.add_argument("--variants", default="eager,graph,graph-nocompile,eager-nocompile,graph-tf32")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--profile", action="store_true", help="also profile 20 steps of each variant")
    args = parser.parse_args()
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else args.device
    print(f"# {name}, torch {torch.__version__}, 9D default network, {args.steps} steps")
    print("| points | variant | warm-up s | steps/s | x eager | max rel. loss diff vs eager | mean loss, last 10 % |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    tail = max(1, args.steps // 10)
    with tempfile.TemporaryDirectory() as tmp:
        for points in args.points:
            baseline = None
            for variant in args.variants.split(","):
                try:
                    warm, rate, losses = train(points, args.steps, variant, Path(tmp), args.device, args.profile)
                except Exception as err:  # one variant's failure is a row, not the end of the run
                    print(f"| {points} | {variant} | failed: {type(err).__name__}: {err} |||||", flush=True)
                    continue
                if baseline is None:
                    baseline = (rate, losses)
                rel = max(abs(a - b) / abs(b) for a, b in zip(losses, baseline[1]))
                print(
                    f"| {points} | {variant} | {warm:.1f} | {rate:.1f} | {rate / baseline[0]:.2f} | {rel:.2e} | "
                    f"{statistics.fmean(losses[-tail:]):.5f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
