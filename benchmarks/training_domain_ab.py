"""A system's plain domain against a wider training box: the same recipe trained on each, wrong claims and exits.

A state's value comes from where its trajectory goes. Where trajectories leave the domain before
their margins decide them, a residual drawn on the domain alone leaves the value there free, and the
network's policy steers by whatever it made of it. A system may declare the wider box its training
draws from (``training_domain()``); this benchmark measures whether one pays before it is declared.

``train`` trains the default recipe (``reach train`` defaults, seed 0, no evaluations) for ``--steps``
steps with its points drawn from ``--box``: ``domain`` (the system's plain domain), ``training-domain``
(its declared ``training_domain()``), or either widened further by ``--widen NAME=LOW:HIGH`` (one per
state, repeatable), the system's hook swapped in this process only. A stopped run resumes where it
stopped when the command is repeated. ``score`` rolls every value function out from the same
``--samples`` uniform states of the domain (``--seed 0``: the model cards' states) under its own
policy with the cards' protocol, and prints its wrong claims and, for the first 2,000 wrong claims'
trajectories, the share that left the domain, through which faces, and the share that left the
wider box as well (``--box`` and ``--widen`` as for ``train``; default: the system's training box).
The rockets (docs/results/training.md, "The rockets' training box")::

    python benchmarks/training_domain_ab.py train --system reachavoidrocketlanding --box domain \\
        --steps 10000 --threads 1 --out runs/ra-rocket-domain/box
    python benchmarks/training_domain_ab.py train --system reachavoidrocketlanding --box domain \\
        --widen y=0:150 --widen vy=-343.43:200 --widen w=-85:85 \\
        --steps 10000 --threads 1 --out runs/ra-rocket-domain/training-domain
    python benchmarks/training_domain_ab.py score runs/ra-rocket-domain/box \\
        runs/ra-rocket-domain/training-domain --samples 100000 --box domain \\
        --widen y=0:150 --widen vy=-343.43:200 --widen w=-85:85

Two runs train side by side on two cores with ``--threads 1`` each; they are compared by steps, not
by wall time.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import torch  # noqa: E402

from reach.systems import ControlAffineSystem, make_system  # noqa: E402
from reach.validation import positive_int_arg  # noqa: E402

#: trajectories recorded per value function to find where its wrong claims go (record keeps every state)
RECORDED = 2000


def widened_box(system: ControlAffineSystem, base: str, widen: list[str]) -> tuple[tuple[float, float], ...]:
    """``base``'s box (``domain`` or ``training-domain``) of ``system`` with each ``NAME=LOW:HIGH`` of
    ``widen`` in place of that state's range (checked by the training as any training box is)."""
    box = list(system.domain if base == "domain" else system.training_domain())
    for item in widen:
        name, _, bounds = item.partition("=")
        low, sep, high = bounds.partition(":")
        if name not in system.state_names or not sep:
            raise SystemExit(
                f"--widen expects NAME=LOW:HIGH with NAME one of {', '.join(system.state_names)}, got {item!r}"
            )
        try:
            box[system.state_names.index(name)] = (float(low), float(high))
        except ValueError:
            raise SystemExit(f"--widen {item!r}: LOW and HIGH must be numbers") from None
    return tuple(box)


def train(system_name: str, base: str, steps: int, threads: int, out: Path, widen: list[str] | None = None) -> None:
    """Train (or resume) the default recipe on ``base``'s box, ``widen``-ed, for ``steps`` steps into ``out``."""
    from training.config import TrainConfig  # lazy: heavy imports after parsing
    from training.trainer import Trainer

    torch.set_num_threads(threads)
    system = make_system(system_name)
    box = widened_box(system, base, widen or [])
    system_type = type(system)
    declared = system_type.__dict__.get("training_domain")
    system_type.training_domain = lambda self: box  # this process only
    try:
        config = TrainConfig(system=system_name, steps=steps, seed=0, eval_every_s=1e9)
        trainer = Trainer.open(config, out, progress=False)
        if trainer.config.steps != steps:
            raise SystemExit(f"{out}: a run of {trainer.config.steps} steps, not {steps}; choose another --out")
        summary = trainer.train()
    finally:
        if declared is None:
            del system_type.training_domain
        else:
            system_type.training_domain = declared
    wall = summary.get("wall_time_s", float("nan"))
    print(f"{out}: points from {box}, {summary.get('steps', steps)} steps, {wall:.0f} s")


def score(
    sources: list[str],
    samples: int,
    seed: int,
    threads: int,
    base: str = "training-domain",
    widen: list[str] | None = None,
) -> None:
    """Wrong claims of every source on the same states, and where the wrong claims' trajectories went."""
    from safety.value_loading import load_value_function  # lazy: heavy imports after parsing
    from safety.verification.rollout import rollout
    from safety.verification.verify import sample_states

    torch.set_num_threads(threads)
    value_functions = []  # every source loaded and checked before any rollout
    for source in sources:
        try:
            value_functions.append((source, load_value_function(source).value_function))
        except ValueError as error:
            raise SystemExit(f"training_domain_ab: {error}") from None
    print(
        "| value function | claims % | wrong claims % | wrong claims leaving the domain | ... the wider box "
        "| through (share of them, >= 0.05) |"
    )
    print("|---|---:|---:|---:|---:|---|")
    for source, vf in value_functions:
        system = vf.system
        x = sample_states(system, samples, seed)
        result = rollout(vf, x, progress=False)
        claims = result.oriented_value > 0
        wrong = claims & result.failed
        recorded = rollout(vf, x[wrong.nonzero().squeeze(1)[:RECORDED]], record=True, progress=False)
        path = recorded.trajectories  # (steps + 1, N, n)
        low = torch.tensor([lo for lo, _ in system.domain], dtype=path.dtype)
        high = torch.tensor([hi for _, hi in system.domain], dtype=path.dtype)
        below, above = (path < low).any(0), (path > high).any(0)  # (N, n)
        faces = []
        for j, name in enumerate(system.state_names):
            if system.periodic[j]:
                continue
            for side, hit, bound in (("<", below, low), (">", above, high)):
                share = float(hit[:, j].double().mean()) if len(hit) else float("nan")
                if share >= 0.05:
                    faces.append(f"{name} {side} {float(bound[j]):g}: {share:.2f}")
        leaving = float((below | above).any(1).double().mean()) if len(path[0]) else float("nan")
        wide = torch.tensor(widened_box(system, base, widen or []), dtype=path.dtype)
        beyond = ((path < wide[:, 0]) | (path > wide[:, 1])).any(0).any(1)
        leaving_wide = float(beyond.double().mean()) if len(path[0]) else float("nan")
        print(
            f"| {source} | {100 * float(claims.double().mean()):.2f} | {100 * float(wrong.double().mean()):.3f} | "
            f"{leaving:.2f} of {recorded.num_states} | {leaving_wide:.2f} | {'; '.join(faces) or '-'} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="train the default recipe on the domain or a wider box")
    t.add_argument("--system", required=True)
    t.add_argument("--box", choices=("domain", "training-domain"), default="domain", help="the box to start from")
    t.add_argument("--widen", action="append", default=[], metavar="NAME=LOW:HIGH", help="one state's range")
    t.add_argument("--steps", type=positive_int_arg, required=True)
    t.add_argument("--threads", type=positive_int_arg, default=1)
    t.add_argument("--out", type=Path, required=True)
    s = sub.add_parser("score", help="wrong claims and where their trajectories went")
    s.add_argument("sources", nargs="+", help="run directories, checkpoints or pretrained:NAME")
    s.add_argument("--samples", type=positive_int_arg, default=100_000)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--threads", type=positive_int_arg, default=2)
    s.add_argument("--box", choices=("domain", "training-domain"), default="training-domain", help="the wider box")
    s.add_argument("--widen", action="append", default=[], metavar="NAME=LOW:HIGH", help="one state's range")
    args = parser.parse_args()
    if args.command == "train":
        train(args.system, args.box, args.steps, args.threads, args.out, args.widen)
    else:
        score(args.sources, args.samples, args.seed, args.threads, args.box, args.widen)


if __name__ == "__main__":
    main()
