"""Training throughput: steps/s and points/s of one HJI-residual training step.

Run: ``python benchmarks/bench_training.py`` (``--quick`` for a smoke run).

Configurations: DeepReach's (layout ssssl = 4 sine layers of 512, 65,000 points per step) on Air3D
and on the 9D system, and the CPU default of ``reach train`` (ssssl, width 128, 8,192 points). Each
is timed over a block of steps (5 for DeepReach's, 200 for the default) after 2 warm-up steps; a
step is sampling, forward, the input gradient, the Hamiltonian, the residual loss, backward and an
Adam update. Three ways of taking the step (``reach train --gradients/--compile``):

* ``autograd``: input gradient by ``torch.autograd.grad(create_graph=True)``, then double backward
  (DeepReach's way);
* ``fused``: input gradient carried through the layers by hand in the forward pass, one backward;
* ``fused + compile``: the same under ``torch.compile`` (compilation happens in the warm-up steps and
  is not timed; the first step of a run pays it, 10-20 s on a 2-core CPU).

``--layouts rrrrl,ssrsl`` adds the CPU default on Air3D with those activation layouts (what a ReLU
layer costs against a sine layer, per step).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

import torch

from training import TrainConfig, Trainer

# (label, system, width, points, timed steps): small configs get more steps so that the one
# checkpoint written when a timed block ends costs under 2 % of it.
CONFIGS = [
    ("DeepReach 4x512, 65k points", "air3d", 512, 65_000, 5),
    ("DeepReach 4x512, 65k points", "multivehicle9d", 512, 65_000, 5),
    ("reach CPU default 4x128, 8192 points", "air3d", 128, 8192, 200),
    ("reach CPU default 4x128, 8192 points", "multivehicle9d", 128, 8192, 200),
]
#: step implementations: label -> (gradients, compile)
METHODS = {"autograd": ("autograd", False), "fused": ("fused", False), "fused + compile": ("fused", True)}


def time_config(
    system: str, width: int, points: int, steps: int, device: str, method: str, layout: str = "ssssl"
) -> float:
    """Seconds per training step of ``reach train``'s loop, timed after 2 warm-up steps."""
    gradients, compile = METHODS[method]
    with tempfile.TemporaryDirectory() as run:
        config = TrainConfig(
            system=system,
            layout=layout,
            width=width,
            points=points,
            steps=2 + steps,
            device=device,
            gradients=gradients,
            compile=compile,
            log_every=10**9,
            checkpoint_every_s=1e9,
        )
        trainer = Trainer(config, run, progress=False)
        trainer.config.steps = 2
        trainer.train()  # warm-up
        trainer.config.steps = 2 + steps
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        trainer.train()
        if device == "cuda":
            torch.cuda.synchronize()
        return (time.perf_counter() - t0) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale-steps", type=float, default=1.0, help="multiply each config's timed steps")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--methods", nargs="+", choices=list(METHODS), default=list(METHODS), help="step implementations to time"
    )
    parser.add_argument(
        "--layouts", default="", help="comma-separated layouts to time beside ssssl (CPU default, Air3D)"
    )
    args = parser.parse_args()
    configs = [(*config, "ssssl") for config in (CONFIGS[2:] if args.quick else CONFIGS)]
    default = CONFIGS[2]
    for layout in filter(None, args.layouts.split(",")):
        configs.append((f"reach CPU default, layout {layout}", *default[1:], layout))
    print(
        f"# Training step throughput on {args.device}: python {platform.python_version()}, torch {torch.__version__}, "
        f"{os.cpu_count()} CPUs, {torch.get_num_threads()} threads\n"
    )
    print("| configuration | system | step | timed steps | s/step | steps/s | points/s | vs autograd |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for label, system, width, points, steps, layout in configs:
        steps = 2 if args.quick else max(1, round(steps * args.scale_steps))
        base = None
        for method in args.methods:
            t = time_config(system, width, points, steps, args.device, method, layout)
            base = t if method == "autograd" else base
            ratio = f"{base / t:.2f}x" if base else "-"
            print(f"| {label} | {system} | {method} | {steps} | {t:.3f} | {1 / t:.2f} | {points / t:,.0f} | {ratio} |")


if __name__ == "__main__":
    main()
