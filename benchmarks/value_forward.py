"""The value-only forward pass with its activations in place, against the same pass allocating.

Run: ``python benchmarks/value_forward.py`` (``--states 72000 --rollout-states 16000 --threads 2``).

Without autograd, :meth:`training.network.ValueNetwork.raw` applies each activation in the layer's
own output (``z.mul_(w0).sin_()`` for a sine layer) instead of allocating ``sin(w0 * z)``. The values
are the same bit for bit; the script checks that, then times, for each shipped network:

* the forward pass alone on ``--states`` states (9 x 8,000 by default: what the greedy policy asks
  of the 9D network for 8,000 states at one step), both ways alternately, ``--repeats`` times each;
* a greedy-policy rollout of ``--rollout-states`` states of the shipped 9D network, both ways, and
  checks that every outcome is the same.

It prints the median milliseconds and their ratio. Time it on a quiet machine: the ratio is what
the change buys where the layers are memory-bound (a CPU); a GPU fuses less and gains less.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time

import torch

import training.network as network_module
from safety.value_loading import load_value_function
from safety.verification.rollout import rollout
from safety.verification.verify import sample_states


def allocating(activation: torch.nn.Module, z: torch.Tensor) -> torch.Tensor:
    """The activation as the module applies it: a new tensor (the path before the change)."""
    return activation(z)


def timed(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        out.append(time.perf_counter() - start)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--states", type=int, default=72_000)
    parser.add_argument("--rollout-states", type=int, default=16_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    in_place = network_module.activate_in_place
    print(f"torch {torch.__version__}, {args.threads} threads, {args.states:,} states, median of {args.repeats}")
    print("| network | allocating (ms) | in place (ms) | ratio | identical |")
    print("|---|---:|---:|---:|---|")
    for name in ("air3d", "multivehicle9d"):
        vf = load_value_function(f"pretrained:{name}").value_function
        x = sample_states(vf.system, args.states, 5)
        t = 0.9 * vf.system.horizon
        network_module.activate_in_place = allocating
        before = vf.value(x, t)
        network_module.activate_in_place = in_place
        after = vf.value(x, t)
        slow, fast = [], []
        call = functools.partial(vf.value, x, t)
        for _ in range(args.repeats):  # alternate, so that a busy spell hits both
            network_module.activate_in_place = allocating
            slow += timed(call, 1)
            network_module.activate_in_place = in_place
            fast += timed(call, 1)
        a, b = statistics.median(slow) * 1e3, statistics.median(fast) * 1e3
        print(f"| {name} | {a:.1f} | {b:.1f} | {a / b:.2f} | {torch.equal(before, after)} |")

    vf = load_value_function("pretrained:multivehicle9d").value_function
    x = sample_states(vf.system, args.rollout_states, 7)
    results = {}
    for label, fn in (("allocating", allocating), ("in place", in_place)):
        network_module.activate_in_place = fn
        start = time.perf_counter()
        results[label] = (rollout(vf, x, policy="greedy", progress=False), time.perf_counter() - start)
    network_module.activate_in_place = in_place
    (r0, t0), (r1, t1) = results["allocating"], results["in place"]
    same = torch.equal(r0.collided, r1.collided) and torch.equal(r0.decided_time, r1.decided_time)
    print(
        f"\ngreedy rollout of {args.rollout_states:,} 9D states: allocating {t0:.1f} s, in place {t1:.1f} s "
        f"({t0 / t1:.2f}x); outcomes identical: {same}"
    )


if __name__ == "__main__":
    main()
