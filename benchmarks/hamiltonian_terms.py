"""Where a trained value meets the HJI residual: by propagating, or by its input term alone.

Run: ``python benchmarks/hamiltonian_terms.py MODEL [MODEL ...] [--samples 20000 --time T --seed 0]``
(``MODEL``: a checkpoint path or ``pretrained:NAME``).

Why: the residual of an avoid or reach problem, ``max(dV/dt - H, V - l)``, is zero wherever ``V = l``
and ``H >= dV/dt``. With a bang-bang input, ``H = grad V . f0 + sum_j |grad V . b_j| u_max``: the input
term is never negative, and it grows with the input's gain. A network can therefore meet the residual
with ``V = l`` everywhere (no propagation at all) plus small ripples in ``V`` along the coordinates the
input drives, whose input term outweighs a negative drift term. Such a value claims every state
outside the failure set, and its policy, read off the ripples, is noise. This prints, on uniform
states at time-to-go ``T`` (default: the horizon), how much of the box has ``V`` within 0.01 of
``l``, and on those states the drift term ``grad V . f0`` and the input term ``H - grad V . f0``:
where the drift term is negative (the value would fall without an input) and ``V = l`` still, the
input term alone holds the residual at zero.

What it measures is a property of the trained network, not a timing; it runs in seconds on a CPU.
"""

from __future__ import annotations

import argparse

import torch

from reach.systems.arrays import TORCH
from safety.verification.verify import sample_states
from training import pretrained
from training.checkpoint import load_network


def terms(model: str, samples: int, time_to_go: float | None, seed: int) -> dict[str, float]:
    """The measurements above for one model."""
    path = pretrained.checkpoint_path(model) if pretrained.is_pretrained(model) else model
    net = load_network(path).eval()
    system = net.system
    t_go = system.horizon if time_to_go is None else time_to_go
    x = sample_states(system, samples, seed).float()
    t = torch.full((samples,), float(t_go))
    xx = x.clone().requires_grad_(True)
    v = net(xx, t)
    (grad,) = torch.autograd.grad(v.sum(), xx)
    v = v.detach()
    with torch.no_grad():
        hamiltonian = system.hamiltonian(x, grad)
        drift = (grad * TORCH.stack(system.drift(list(x.T), TORCH), like=x[:, 0])).sum(-1)
        inputs = hamiltonian - drift
        flat = (v - system.terminal_margin(x)).abs() < 0.01
        held = flat & (drift < 0)
    return {
        "V within 0.01 of l": float(flat.float().mean()),
        "... and drift term < 0": float(held.float().mean()),
        "drift term there (mean)": float(drift[held].mean()) if bool(held.any()) else float("nan"),
        "input term there (mean)": float(inputs[held].mean()) if bool(held.any()) else float("nan"),
        "input term, all states (mean)": float(inputs.mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+")
    parser.add_argument("--samples", type=int, default=20000)
    parser.add_argument("--time", type=float, default=None, help="time-to-go (default: the horizon)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rows = {m: terms(m, args.samples, args.time, args.seed) for m in args.models}
    names = list(next(iter(rows.values())))
    print(f"{args.samples} uniform states (seed {args.seed}), time-to-go {args.time or 'the horizon'}")
    print("| model | " + " | ".join(names) + " |")
    print("|---|" + "---:|" * len(names))
    for model, row in rows.items():
        print(f"| {model} | " + " | ".join(f"{row[n]:.3f}" for n in names) + " |")


if __name__ == "__main__":
    main()
