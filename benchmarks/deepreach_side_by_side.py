"""DeepReach's public release beside ``reach train``, at one wall budget, scored by one ``reach evaluate``.

Issue 63, item 4. For each system, on the CPU, one after the other:

1. DeepReach's own ``run_experiment.py`` (github:smlbansal/deepreach, branch ``public_release``,
   extracted from a git directory to a temporary folder; nothing of it is copied into this repository)
   trains with its own defaults: a 3x512 sine network (``--num_hl 3 --num_nl 512``), 65,000 points a
   step, Adam at a constant 2e-5, no pretraining, a linear time curriculum over ``--num_epochs``
   (100,000) epochs, adaptive loss weighting. The harness sets only what the problem and the CPU need:

   * the system's physics and horizon (``--dynamics_class`` and its arguments, ``--tMax``), read from
     our system so both sides solve one problem; ``--minWith target`` (the BRT, as DeepReach's README);
   * ``--steps_til_summary 1``: the release writes ``model_current.pth`` every this many steps (default
     100, many minutes of CPU at 65,000 points); at 1 the state at the budget is at most one step old;
   * in its process (the ``_run-deepreach-on-cpu`` entry below, which then runs the script unchanged):
     ``.cuda()`` of modules and tensors is the identity (the release calls it unconditionally),
     ``torch.set_num_threads(--threads)``, ``model_current.pth`` is written atomically (a file beside
     it records the updates it holds), and the modules its training never calls (``wandb`` without
     ``--use_wandb``, ``plotly``, ``scipy``, ``sklearn``) are stand-ins when not installed: any use of
     one raises.

   The harness kills it ``--budget`` after its script starts and takes that last state.
   ``--deepreach-arg KEY=VALUE`` passes any other option of the release (say ``counter_end=15``, a
   curriculum that ends inside the budget while training goes on at the full horizon), and the output
   lists each.
2. ``training.deepreach.load_deepreach`` imports that state (the release's ``diff_model``); its
   boundary error ``|V(x, 0) - l(x)|`` and its largest gap to DeepReach's own value of the same file
   (its ``io_to_value``, run in a process of its own, the ``_deepreach-values`` entry) are printed, and
   the network is saved as a reach checkpoint.
3. ``reach train --system NAME --budget BUDGET --seed 0`` trains our recipe for the same budget (or
   ``--ours pretrained`` takes the shipped model, when its card's budget is the same).
4. One ``reach evaluate`` scores both on the same states, with the settings of the system's card
   (samples, scenario samples, robust samples, seed, and its ground truth when the card names one;
   solved first with ``reach groundtruth NAME --grid 101`` when missing). ``--samples`` and the like
   override them; ``--eval-device cuda`` scores on a GPU.

It prints what it measured and how (CPU, torch threads, budget, steps each side made, the DeepReach
commit) and writes ``OUT/side_by_side.json`` and ``OUT/NAME/scores.csv``. Run::

    python benchmarks/deepreach_side_by_side.py --systems air3d,reachavoidrocketlanding

Each system trains for its recipe's budget unless ``--budget`` is given (Air3D 10 minutes, the rocket two
hours). Measurements and the exact commands run: docs/results/training.md, "Side by side with DeepReach's code".

DeepReach needs ``pip install configargparse`` (its argument parser) beside this project's packages;
the git directory is ``--deepreach-git`` (for example a ``git clone --bare
https://github.com/smlbansal/deepreach``) or an existing checkout ``--deepreach-dir``.
"""

from __future__ import annotations

import argparse
import csv
import importlib
import json
import math
import os
import platform
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
#: the public_release commit this harness was written against (the output names the one it ran)
PINNED = "2c3bf674d7c8fd3c8653e5f9ddaeabbe2a346c8a"
MIRROR = Path("/work/.mirror/smlbansal+deepreach/repo")
#: our recipe's wall budget per system (the default ``--budget``): Air3D's card trains ``--budget 10m``; the
#: rocket's catalogue recipe is two hours of the quiet 2-core CPU (benchmarks/catalogue_recipes.py)
RECIPE_BUDGETS = {"air3d": "10m", "reachavoidrocketlanding": "2h"}
RUNNER = "_run-deepreach-on-cpu"
VALUES = "_deepreach-values"
#: modules the release imports at the top but its training never calls
UNUSED_IMPORTS = ("wandb", "plotly", "plotly.express", "scipy", "scipy.io", "sklearn", "sklearn.svm")
#: score columns printed side by side (those present in the table)
COLUMNS = (
    "violation_rate",
    "false_safe_rate",
    "false_reachable_rate",
    "scenario_volume",
    "eps",
    "delta",
    "iou_volume",
    "mse_volume",
)


# ---------------------------------------------------------------- inside DeepReach's process
def _stand_in(name: str) -> Any:
    import importlib.machinery  # lazy: only the DeepReach process needs stand-in modules
    import types  # lazy: as above

    module = types.ModuleType(name)
    module.__spec__ = importlib.machinery.ModuleSpec(name, None)  # find_spec (torch._dynamo) asks for one

    def missing(attr: str) -> Any:
        if attr.startswith("__"):
            raise AttributeError(attr)
        raise RuntimeError(f"{name}.{attr}: {name} is not installed; the harness stood it in as unused")

    module.__getattr__ = missing  # type: ignore[method-assign]
    return module


def run_deepreach_on_cpu(argv: list[str]) -> None:
    """Run the release's ``run_experiment.py`` in this process on the CPU (see the module docstring).

    ``argv``: checkout, threads, clock file, then the script's own arguments."""
    import importlib.util  # lazy: this entry runs in DeepReach's process only
    import runpy  # lazy: as above

    import torch  # lazy: as above

    checkout, threads, clock = Path(argv[0]), int(argv[1]), Path(argv[2])
    torch.set_num_threads(threads)
    torch.nn.Module.cuda = lambda self, device=None: self  # type: ignore[method-assign]
    torch.Tensor.cuda = lambda self, *args, **kwargs: self  # type: ignore[method-assign]
    absent = {name.split(".")[0] for name in UNUSED_IMPORTS if importlib.util.find_spec(name.split(".")[0]) is None}
    for name in UNUSED_IMPORTS:
        parent = name.split(".")[0]
        if parent in absent:
            sys.modules[name] = _stand_in(name)
            if "." in name:
                setattr(sys.modules[parent], name.split(".")[1], sys.modules[name])
    every = int(argv[argv.index("--steps_til_summary") + 1]) if "--steps_til_summary" in argv else 100
    save = torch.save
    saves = [0]
    start = time.time()

    def atomic_save(obj: Any, f: Any, *args: Any, **kwargs: Any) -> None:
        if not (isinstance(f, str) and f.endswith("model_current.pth")):
            return save(obj, f, *args, **kwargs)
        save(obj, f + ".tmp", *args, **kwargs)
        os.replace(f + ".tmp", f)
        # the release saves at the start of step k (k = 0, every, 2 every, ...): k updates are in it
        record = {"updates": saves[0] * every, "script_s": time.time() - start}
        Path(f + ".json.tmp").write_text(json.dumps(record))
        os.replace(f + ".json.tmp", f + ".json")
        saves[0] += 1
        return None

    torch.save = atomic_save
    clock.write_text(json.dumps({"start": start}))
    sys.path.insert(0, str(checkout))
    os.chdir(checkout)
    sys.argv = ["run_experiment.py", *argv[3:]]
    runpy.run_path(str(checkout / "run_experiment.py"), run_name="__main__")


def deepreach_values(argv: list[str]) -> None:
    """DeepReach's own value of its checkpoint (its ``SingleBVPNet`` and ``io_to_value``) at saved coordinates.

    ``argv``: checkout, checkpoint, coordinates (``(t, x)`` rows), output file, then the problem's arguments."""
    import inspect  # lazy: this entry runs in a process of its own

    import torch  # lazy: as above

    checkout, checkpoint, coords_path, out_path, *problem = argv
    sys.path.insert(0, checkout)
    dynamics = importlib.import_module("dynamics.dynamics")
    modules = importlib.import_module("utils.modules")
    options = dict(zip(problem[0::2], problem[1::2], strict=True))
    cls = getattr(dynamics, options["--dynamics_class"])
    params = {k: v for k, v in inspect.signature(cls).parameters.items() if k != "self"}
    if any(v.annotation is bool for v in params.values()):
        raise ValueError(f"{cls.__name__}: boolean arguments are not set up here")
    system = cls(**{k: v.annotation(options[f"--{k}"]) for k, v in params.items()})
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    hidden = sum(1 for k in state if k.endswith(".weight")) - 2
    model = modules.SingleBVPNet(
        in_features=system.input_dim,
        type="sine",
        hidden_features=state["net.net.0.0.weight"].shape[0],
        num_hidden_layers=hidden,
    )
    model.load_state_dict(state)
    results = model({"coords": system.coord_to_input(torch.load(coords_path, weights_only=True))})
    values = system.io_to_value(results["model_in"], results["model_out"].squeeze(dim=-1))
    torch.save(values.detach(), out_path)


# ---------------------------------------------------------------- the harness
def deepreach_problem(name: str) -> tuple[Any, list[str]]:
    """Our system ``name`` and the release's arguments that pose the same problem."""
    from reach.systems import make_system  # lazy: keep the DeepReach entry free of reach imports

    system = make_system(name)
    if name == "air3d":
        same = system.evader_speed == system.pursuer_speed
        if not same or system.evader_max_turn_rate != system.pursuer_max_turn_rate:
            raise ValueError("air3d: DeepReach's Air3D has one speed and one turn rate for both aircraft")
        alpha = system.deepreach.state_scale[2] / math.pi
        args = ["--dynamics_class", "Air3D", "--collisionR", str(system.collision_radius)]
        args += ["--velocity", str(system.evader_speed), "--omega_max", str(system.evader_max_turn_rate)]
        args += ["--angle_alpha_factor", f"{alpha:.12g}"]
    elif name == "reachavoidrocketlanding":
        args = ["--dynamics_class", "ReachAvoidRocketLanding"]
    else:
        raise ValueError(f"--systems: no DeepReach counterpart set up for {name!r} (air3d, reachavoidrocketlanding)")
    return system, [*args, "--minWith", "target", "--tMax", f"{system.horizon:.12g}"]


def extract(args: argparse.Namespace, into: Path) -> tuple[Path, str]:
    """The release's files in a folder, and their commit."""
    if args.deepreach_dir is not None:
        checkout = Path(args.deepreach_dir).resolve()
        head = subprocess.run(["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True)
        return checkout, head.stdout.strip() if head.returncode == 0 else "unknown (not a git checkout)"
    git = Path(args.deepreach_git)
    if not git.exists():
        raise SystemExit(f"--deepreach-git {git}: not found (git clone --bare https://github.com/smlbansal/deepreach)")
    commit = subprocess.run(
        ["git", "--git-dir", str(git), "rev-parse", args.ref], check=True, capture_output=True, text=True
    ).stdout.strip()
    checkout = into / "deepreach"
    checkout.mkdir(parents=True)
    archive = subprocess.run(["git", "--git-dir", str(git), "archive", commit], check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(checkout)], input=archive.stdout, check=True)
    return checkout, commit


def train_deepreach(checkout: Path, problem: list[str], out: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Run the release until the budget; returns its last state's path, updates and times."""
    extra = [item for pair in args.deepreach_arg for item in (f"--{pair[0]}", pair[1])]
    script = ["--mode", "train", "--experiment_class", "DeepReach", "--experiments_dir", str(out)]
    script += ["--experiment_name", "run", *problem, "--steps_til_summary", "1", *extra]
    clock = out / "clock.json"
    out.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, str(Path(__file__).resolve()), RUNNER, str(checkout), str(args.threads), str(clock)]
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": "", "MPLBACKEND": "Agg", "WANDB_MODE": "disabled"}
    env["OMP_NUM_THREADS"] = str(args.threads)
    launched = time.time()
    with open(out / "log.txt", "w") as log:
        proc = subprocess.Popen(
            [*command, *script], stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
        deadline, started = launched + args.budget_s + 60.0, False  # the budget counts from the script's start
        while proc.poll() is None and time.time() < deadline:
            if not started and clock.exists():
                deadline, started = json.loads(clock.read_text())["start"] + args.budget_s, True
            time.sleep(0.2)
        stopped = proc.poll() is None
        if stopped:
            os.killpg(proc.pid, signal.SIGKILL)  # the process group this harness started
        proc.wait()
    ended = time.time()
    current = out / "run" / "training" / "checkpoints" / "model_current.pth"
    if not current.is_file():
        tail = (out / "log.txt").read_text()[-3000:]
        raise SystemExit(f"DeepReach wrote no model_current.pth (exit {proc.returncode}); its log ends:\n{tail}")
    record = json.loads(Path(str(current) + ".json").read_text())
    lines = [ln for ln in (out / "log.txt").read_text().splitlines() if ln.startswith("Epoch ")]
    start = json.loads(clock.read_text())["start"]
    return {
        "checkpoint": str(current),
        "updates_in_checkpoint": record["updates"],
        "checkpoint_at_s": record["script_s"],
        "steps_finished": int(lines[-1].split(",")[0].split()[1]) + 1 if lines else 0,
        "script_wall_s": ended - start,
        "process_wall_s": ended - launched,
        "killed_at_budget": stopped,
        "exit_code": proc.returncode,
        "command": shlex.join(["python", "run_experiment.py", *script]),
    }


def import_deepreach(path: str, system: Any, target: Path, metadata: dict[str, Any], layout: str) -> tuple[float, Any]:
    """Import the release's state with ``load_deepreach`` and save it as a reach checkpoint; returns
    its boundary error (relative mean ``|V(x, 0) - l(x)|``; scored whatever it is)."""
    from training.checkpoint import save_checkpoint  # lazy: keep the DeepReach entry free of reach imports
    from training.deepreach import check_boundary_condition, load_deepreach  # lazy: as above

    net = load_deepreach(path, system, layout, check_boundary=False, model="diff")
    try:
        error = check_boundary_condition(net, path, layout)
    except ValueError as err:
        print(f"  note: {err}")
        error = float(str(err).split(" is ")[1].split(" ")[0])
    save_checkpoint(target, net, metadata={"imported_from": "DeepReach public_release", **metadata})
    return error, net


def import_gap(net: Any, checkout: Path, path: str, problem: list[str], work: Path) -> float:
    """Largest ``|V_imported - V_deepreach|`` on 2,000 uniform ``(t, x)``, DeepReach's value computed by its
    own code in a process of its own: the import is checked, not assumed."""
    import torch  # lazy: the DeepReach entries import torch themselves

    system = net.system
    generator = torch.Generator().manual_seed(1)
    x = system.sample_states(2000, generator=generator, dtype=torch.float32)
    t = torch.rand(2000, generator=generator) * system.horizon
    torch.save(torch.cat([t[:, None], x], dim=1), work / "coords.pt")
    command = [sys.executable, str(Path(__file__).resolve()), VALUES, str(checkout), path]
    command += [str(work / "coords.pt"), str(work / "values.pt"), *problem]
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": "", "OMP_NUM_THREADS": "1"}
    subprocess.run(command, check=True, capture_output=True, env=env)
    theirs = torch.load(work / "values.pt", weights_only=True)
    with torch.no_grad():
        return float((net(x, t) - theirs).abs().max())


def card(name: str) -> dict[str, Any]:
    return json.loads((ROOT / "training" / "pretrained" / f"{name}.card.json").read_text())


def evaluation_flags(name: str, args: argparse.Namespace) -> list[str]:
    """``reach evaluate`` settings of the system's card, with this run's overrides."""
    ev = card(name)["evaluation"]
    given = {"samples": args.samples, "scenario_samples": args.scenario_samples, "robust_samples": args.robust_samples}
    flags = ["--seed", str(ev.get("seed", 0))]
    for key, value in given.items():
        value = ev.get(key) if value is None else value
        if value is not None:
            flags += [f"--{key.replace('_', '-')}", str(value)]
    words = shlex.split(ev["command"])
    if "--ground-truth" in words and not args.no_ground_truth:
        gt = ROOT / words[words.index("--ground-truth") + 1]
        if not gt.is_file():
            solve = [sys.executable, "-m", "reach", "groundtruth", name, "--grid", "101", "--out", str(gt)]
            print(f"  solving the card's ground truth: {shlex.join(solve[1:])}", flush=True)
            subprocess.run(solve, check=True, cwd=ROOT)
        flags += ["--ground-truth", str(gt)]
    return flags


def reach(args: argparse.Namespace, *words: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "reach", "--threads", str(args.threads), *words]
    print(f"  $ {shlex.join(['reach', *command[3:]])}", flush=True)
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    if done.returncode:
        raise SystemExit(f"reach {words[0]} failed ({done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return done


def ours(name: str, out: Path, args: argparse.Namespace) -> tuple[str, dict[str, Any]]:
    """Our recipe's model for the budget: trained now, or the shipped one."""
    from training.config import parse_duration  # lazy: keep the DeepReach entries free of reach imports

    if args.ours == "pretrained":
        trained = card(name)["training"]
        words = shlex.split(trained["command"])
        if "--budget" not in words or parse_duration(words[words.index("--budget") + 1]) != args.budget_s:
            raise SystemExit(f"{name}: the shipped model was not trained for {args.budget_s:g} s; use --ours train")
        return f"pretrained:{name}", {"steps": trained["steps"], "wall_time_s": trained["wall_time_s"], "shipped": True}
    run = out / "reach-train"
    reach(args, "train", "--system", name, "--budget", f"{args.budget_s:g}s", "--seed", "0", "--out", str(run))
    meta = json.loads((run / "checkpoint.json").read_text())
    return str(run), {"steps": meta["steps"], "wall_time_s": meta["wall_time_s"], "shipped": False}


def compare(name: str, checkout: Path, commit: str, args: argparse.Namespace) -> dict[str, Any]:
    from training.config import parse_duration  # lazy: keep the DeepReach entries free of reach imports

    if args.budget is None and name not in RECIPE_BUDGETS:
        raise SystemExit(f"{name}: no recipe budget known; give --budget")
    args = argparse.Namespace(**vars(args), budget_s=parse_duration(args.budget or RECIPE_BUDGETS[name]))
    out = Path(args.out).resolve() / name
    if out.exists():
        raise SystemExit(f"{out} exists; give another --out")
    system, problem = deepreach_problem(name)
    print(f"[{name}] DeepReach public_release, {args.budget_s:g} s on {args.threads} threads", flush=True)
    theirs = train_deepreach(checkout, problem, out / "deepreach", args)
    hidden = dict(args.deepreach_arg).get("num_hl", "3")
    layout = "s" * (int(hidden) + 1) + "l"
    target = out / "deepreach-public-release.pt"
    meta = {"deepreach_commit": commit, "updates": theirs["updates_in_checkpoint"]}
    theirs["boundary_error"], net = import_deepreach(theirs["checkpoint"], system, target, meta, layout)
    theirs["import_max_abs_gap"] = import_gap(net, checkout, theirs["checkpoint"], problem, out / "deepreach")
    what = "the shipped model (its card's budget)" if args.ours == "pretrained" else f"reach train, {args.budget_s:g} s"
    print(f"[{name}] ours: {what}", flush=True)
    source, our_run = ours(name, out, args)
    table = out / "scores.csv"
    print(f"[{name}] reach evaluate, both models on the same states", flush=True)
    device = [] if args.eval_device is None else ["--device", args.eval_device]
    reach(args, "evaluate", source, str(target), *evaluation_flags(name, args), *device, "--out", str(table))
    with open(table) as fh:
        rows = list(csv.DictReader(fh))
    result = {"system": name, "budget_s": args.budget_s, "deepreach": theirs, "ours": our_run, "scores": rows}
    return {**result, "table": str(table)}


def hardware() -> str:
    model = platform.processor() or "unknown CPU"
    with open("/proc/cpuinfo") as fh:
        names = [line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")]
    return f"{names[0] if names else model}, {os.cpu_count()} logical cores"


def report(results: list[dict[str, Any]], commit: str, args: argparse.Namespace) -> None:
    import torch  # lazy: the DeepReach entry imports torch itself

    print(f"\nhardware: {hardware()}; torch {torch.__version__}, {args.threads} threads each side, one after the other")
    print(f"DeepReach public_release at {commit}; each side trains for the system's budget, on the CPU")
    if commit != PINNED:
        print(f"  (note: not the commit this harness was written against, {PINNED})")
    print(f"DeepReach options set beyond its defaults: {args.deepreach_arg or 'none'} (and those the docstring lists)")
    for res in results:
        dr, us = res["deepreach"], res["ours"]
        print(
            f"\n{res['system']}, {res['budget_s']:g} s each: DeepReach {dr['updates_in_checkpoint']} updates in its "
            "last state "
            f"({dr['steps_finished']} steps finished in {dr['script_wall_s']:.0f} s; boundary error "
            f"{dr['boundary_error']:.3f}, import within {dr['import_max_abs_gap']:.1e} of DeepReach's own value); "
            f"reach train {us['steps']} steps in {us['wall_time_s']:.0f} s"
            + (" (shipped model)" if us["shipped"] else "")
        )
        present = [c for c in COLUMNS if any(row.get(c) not in (None, "") for row in res["scores"])]
        print("  " + " | ".join(["model", *present]))
        for row in res["scores"]:
            print("  " + " | ".join([row.get("label") or row.get("source", "?"), *(row.get(c, "") for c in present)]))
            if row.get("scenario_error"):
                print(f"    ({row.get('label')}: {row['scenario_error']})")
        print(f"  table: {res['table']}")


def key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key or key in ("mode", "experiments_dir", "experiment_name", "dynamics_class"):
        raise argparse.ArgumentTypeError(f"--deepreach-arg takes KEY=VALUE of a free option, got {text!r}")
    if (key == "model" and value != "sine") or (key == "model_mode" and value != "mlp"):
        raise argparse.ArgumentTypeError(f"{text}: the importer reads sine MLPs only")
    return key, value


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in (RUNNER, VALUES):
        (run_deepreach_on_cpu if argv[0] == RUNNER else deepreach_values)(argv[1:])
        return 0
    from training.config import parse_duration  # lazy: keep the DeepReach entries free of reach imports

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--systems", default="air3d,reachavoidrocketlanding", help="comma-separated")
    p.add_argument("--budget", default=None, help="each side's training wall budget, 90s, 10m, 2h (default: recipe's)")
    p.add_argument("--threads", type=int, default=2, help="torch threads of each side")
    p.add_argument("--deepreach-git", default=str(MIRROR), help="a git directory of github:smlbansal/deepreach")
    p.add_argument("--ref", default="public_release", help="the branch or commit to extract")
    p.add_argument("--deepreach-dir", default=None, help="an existing checkout instead (used as it is)")
    p.add_argument("--deepreach-arg", type=key_value, action="append", default=[], help="KEY=VALUE, repeatable")
    p.add_argument("--ours", choices=["train", "pretrained"], default="train")
    p.add_argument("--samples", type=int, default=None, help="override the card's --samples")
    p.add_argument("--scenario-samples", type=int, default=None, help="override the card's")
    p.add_argument("--robust-samples", type=int, default=None, help="override the card's")
    p.add_argument("--eval-device", default=None, help="reach evaluate's --device (training stays on the CPU)")
    p.add_argument("--no-ground-truth", action="store_true", help="score without the card's ground truth")
    p.add_argument("--out", default="runs/deepreach_side_by_side")
    args = p.parse_args(argv)
    try:  # refuse bad settings before anything trains
        _ = args.budget is None or parse_duration(args.budget)
        _ = [deepreach_problem(name) for name in args.systems.split(",")]
    except ValueError as err:
        raise SystemExit(str(err)) from err
    taken = [name for name in args.systems.split(",") if (Path(args.out) / name).exists()]
    if taken:
        raise SystemExit(f"{args.out}: already holds {taken}; give another --out")
    if args.threads < 1:
        raise SystemExit(f"--threads must be >= 1, got {args.threads}")
    with tempfile.TemporaryDirectory(prefix="deepreach-") as tmp:
        checkout, commit = extract(args, Path(tmp))
        results = [compare(name, checkout, commit, args) for name in args.systems.split(",")]
    report(results, commit, args)
    summary = {"commit": commit, "threads": args.threads, "hardware": hardware()}
    summary |= {"deepreach_args": args.deepreach_arg, "results": results}
    (Path(args.out) / "side_by_side.json").write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
