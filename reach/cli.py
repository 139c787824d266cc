"""``reach``: the command line of the reach toolkit.

Subcommands only parse arguments and call library functions: ``envs`` (list environments and
scenes), ``record`` (run an episode and save a GIF), ``groundtruth`` (grid BRT solve), ``train``
(value networks), ``evaluate`` (rollout verification across checkpoints), ``filter-eval`` (what a
safety filter changes in episodes of a task), ``plot`` (BRT slices, union overlays, violation
bars, safety-filtered episode GIFs), ``sweep`` (layouts x seeds trained on a budget and scored along
training, with a report) and ``demo`` (all of it on Air3D, with a report).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path


def _cmd_envs(args: argparse.Namespace) -> int:
    import reach_envs
    from reach_envs.scenes import SCENES

    print("Gymnasium environments:")
    for env_id, scene_name in reach_envs.ENV_SCENES.items():
        scene = SCENES[scene_name]()
        s = scene.system
        print(
            f"  {env_id:<20} scene={scene_name:<20} state={s.state_dim}D action={s.control_dim} "
            f"disturbance={scene.disturbance or 'none'} dt={scene.dt} horizon={scene.episode_horizon}"
        )
    print("Named scenes (gym.make(id, scene=NAME) or reach_envs.parallel.parallel_env(NAME)):")
    for name, factory in SCENES.items():
        scene = factory()
        print(f"  {name:<20} system={scene.system.name:<15} cars={len(scene.system.car_names)}")
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    import gymnasium as gym

    import reach_envs  # noqa: F401  (registers the environments)
    from reach_envs.recording import record_episode

    kwargs = {"scene": args.scene} if args.scene else {}
    env = gym.make(args.env, render_mode="rgb_array", **kwargs)
    if args.policy == "random":
        env.action_space.seed(args.seed)

        def policy(obs):
            return env.action_space.sample()
    else:
        policy = None
    summary = record_episode(env, args.out, policy=policy, seed=args.seed, every=args.every)
    env.close()
    print(
        f"wrote {summary['path']}: {summary['steps']} steps, {summary['frames']} frames, "
        f"collision={summary['collision']}"
    )
    return 0


def _parse_times(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError as err:
        raise ValueError(f"--times must be comma-separated numbers, got {text!r}") from err


def _cmd_groundtruth(args: argparse.Namespace) -> int:
    import torch

    from groundtruth import solve
    from groundtruth.plotting import plot_zero_level_slices
    from reach.systems import make_system

    system = make_system(args.system)
    horizon = args.horizon if args.horizon is not None else system.horizon
    times = _parse_times(args.times) if args.times else [horizon]
    if any(t > horizon + 1e-12 for t in times):
        raise ValueError(f"--times {times} go beyond --horizon {horizon}")
    if not times or abs(times[-1] - horizon) > 1e-12:
        times.append(horizon)
    grid = [int(v) for v in args.grid.split(",")] if "," in args.grid else int(args.grid)
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    solution = solve(
        system,
        grid,
        times,
        cfl=args.cfl,
        dissipation=args.dissipation,
        dtype=dtype,
        device=args.device,
        compile=None if args.compile == "auto" else args.compile == "on",
    )
    path = solution.save(args.out)
    scheme = solution.metadata["scheme"]
    print(
        f"wrote {path}: {system.name} on {'x'.join(map(str, solution.grid.shape))}, times {times}, "
        f"{scheme['steps']} steps, {solution.metadata['wall_time_s']:.1f} s"
    )
    if args.plot:
        print(f"wrote {plot_zero_level_slices(solution, args.plot)}")
    return 0


def _given(**options: object) -> dict[str, object]:
    """The options the user gave (not None): the rest keep :class:`TrainConfig`'s defaults."""
    return {key: value for key, value in options.items() if value is not None}


def _optional_float(text: str) -> float | str:
    """A float, or ``"off"``."""
    if text.strip().lower() == "off":
        return "off"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or 'off', got {text!r}") from None


def _cmd_train(args: argparse.Namespace) -> int:
    from training import TrainConfig, Trainer, TrainingDivergedError, parse_duration
    from training.evaluate import ReferenceEvaluator

    evaluator = None
    if args.groundtruth:
        from groundtruth import GridSolution

        reference = GridSolution.load(args.groundtruth, outside="clamp")
        t_eval = args.eval_time if args.eval_time is not None else float(reference.times[-1])
        evaluator = ReferenceEvaluator(reference, t_eval)
    budget = parse_duration(args.budget) if args.budget else None
    if args.resume:
        trainer = Trainer.resume(
            args.resume, evaluator=evaluator, steps=args.steps, budget_s=budget, tensorboard=args.tensorboard or None
        )
    else:
        if not args.out:
            raise ValueError("give --out RUN_DIR for a new run (or --resume RUN_DIR)")
        encoding_and_penalty = _given(
            sincos=args.sincos,
            sincos_radius=args.sincos_radius,
            gradient_bound=args.gradient_bound,
            gradient_weight=args.gradient_weight,
        )
        if encoding_and_penalty.get("gradient_bound") == "off":
            encoding_and_penalty["gradient_bound"] = None
        config = TrainConfig(
            system=args.system,
            layout=args.layout,
            width=args.width,
            w0=args.w0,
            parameterisation=args.parameterisation,
            points=args.points,
            lr=args.lr,
            lr_final=args.lr_final,
            schedule=args.schedule,
            loss=args.loss,
            gradients=args.gradients,
            compile={"auto": None, "on": True, "off": False}[args.compile],
            curriculum=args.curriculum,
            pretrain=args.pretrain,
            steps=args.steps,
            budget_s=budget,
            target_loss=args.target_loss,
            seed=args.seed,
            device=args.device,
            log_every=args.log_every,
            checkpoint_every_s=args.checkpoint_every,
            eval_every_s=args.eval_every,
            snapshots=args.snapshots,
            tensorboard=args.tensorboard,
            **encoding_and_penalty,
        )
        if (Path(args.out) / "checkpoint.pt").exists():
            raise ValueError(f"{args.out} already holds a run; use --resume {args.out} to continue it")
        trainer = Trainer(config, args.out, evaluator=evaluator)
    try:
        summary = trainer.train()
    except TrainingDivergedError as err:
        print(f"reach train: {err}", file=sys.stderr)
        return 3
    print(f"{summary['run_dir']}: {summary['steps']} steps in {summary['wall_time_s']:.1f} s ({summary['stopped']})")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from safety.evaluate import evaluate_many, markdown_table
    from safety.plots import plot_violation_bars
    from safety.verify import VerifySettings

    settings = VerifySettings(
        samples=args.samples,
        certify_samples=args.certify_samples,
        beta=args.beta,
        seed=args.seed,
        dt=args.dt,
        integrator=args.integrator,
        matmul_precision=args.matmul_precision,
        horizon=args.horizon,
        chunk_size=args.chunk_size,
    )
    rows = evaluate_many(
        args.sources,
        args.out,
        settings,
        system=args.system,
        format=args.format,
        layout=args.layout,
        ground_truth=args.ground_truth,
        gt_time=args.gt_time,
        pairwise=args.pairwise,
        device=args.device,
    )
    print(markdown_table(rows))
    out = Path(args.out)
    print(f"\nwrote {out.with_suffix('.csv')}, {out.with_suffix('.json')}, {out.with_suffix('.md')}")
    if args.plot and any(not r.get("error") for r in rows):
        print(f"wrote {plot_violation_bars(rows, out.with_name(out.stem + '_violations.png'))}")
    return 1 if all(r.get("error") for r in rows) else 0


def _cmd_plot(args: argparse.Namespace) -> int:
    from safety import plots
    from safety.evaluate import expand_sources, load_results
    from safety.value_functions import load_value_function

    if args.kind == "bars":
        rows = load_results(args.sources[0])
        print(f"wrote {plots.plot_violation_bars(rows, args.out)}")
        return 0
    if args.kind == "episode":
        summary = plots.record_filtered_episode(
            args.sources[0], args.out, scene=args.scene, threshold=args.threshold, seed=args.seed
        )
        print(f"wrote {summary['path']}: {summary['steps']} steps, collision={summary['collision']}")
        return 0
    loaded = [
        load_value_function(p, format=args.format, system=args.system, layout=args.layout)
        for p in expand_sources(args.sources)
    ]
    vfs = [(lv.label, lv.value_function) for lv in loaded]
    system = vfs[0][1].system
    slices = [plots.parse_slice(s, system) for s in args.slice] if args.slice else None
    if args.kind == "union":
        if not args.pairwise:
            raise ValueError("plot union needs --pairwise PAIR.npz (reach groundtruth relativepair ...)")
        union = load_value_function(args.pairwise, format="grid", system=system).value_function
        print(f"wrote {plots.plot_union_overlay(vfs, union, args.out, slices=slices, t=args.t)}")
        return 0
    reference = load_value_function(args.ground_truth).value_function if args.ground_truth else None
    print(f"wrote {plots.plot_brt_slices(vfs, args.out, t=args.t, slices=slices, reference=reference)}")
    return 0


def _cmd_filter_eval(args: argparse.Namespace) -> int:
    from reach_envs.scenes import make_scene
    from safety.evaluate import expand_sources
    from safety.filter_eval import (
        FilterConfig,
        evaluate_filter_parallel,
        evaluate_filters,
        filter_table,
        outside_states,
        record_side_by_side,
        worst_case_disturbance,
        write_filter_results,
    )
    from safety.plots import plot_filter_tradeoff
    from safety.value_functions import load_value_function

    scene = make_scene(args.scene)
    system = scene.system
    loaded = [
        load_value_function(p, format=args.format, system=system, layout=args.layout)
        for p in (expand_sources(args.value_functions) if args.value_functions else [])
    ]
    overrides: dict = {}
    if args.pursuer != "scene":
        if not system.disturbance_dim:
            raise ValueError(f"--pursuer {args.pursuer}: scene {args.scene} has no disturbance input")
        if args.pursuer == "worst-case":
            source = args.adversary or (str(loaded[0].path) if loaded else None)
            if source is None:
                raise ValueError("--pursuer worst-case needs --adversary VF (or a value function to filter with)")
            adversary = load_value_function(source, system=system).value_function
            overrides["disturbance"] = worst_case_disturbance(adversary)
        else:
            overrides["disturbance"] = args.pursuer
    initial = None
    if args.start_outside:
        reference = load_value_function(args.start_outside, system=system).value_function
        initial = outside_states(reference, args.episodes, args.start_margin, args.seed)
    thresholds = [float(v) for v in args.thresholds.split(",")] if args.thresholds else [None]
    configs = [FilterConfig("nominal")]
    for lv in loaded:
        configs += [FilterConfig(lv.label, lv.value_function, th) for th in thresholds]
    ttg = args.time_to_go if args.time_to_go in (None, "remaining") else float(args.time_to_go)
    if args.pettingzoo:
        rows = [
            evaluate_filter_parallel(scene, c, args.episodes, args.seed, ttg, scene_overrides=overrides)
            for c in configs
        ]
    else:
        rows = evaluate_filters(
            scene, configs, args.episodes, args.seed, ttg, scene_overrides=overrides, initial_states=initial
        )
    header = {
        "format": "reach.filter-eval.v1",
        "scene": args.scene,
        "episodes": args.episodes,
        "seed": args.seed,
        "pursuer": args.pursuer,
        "time_to_go": args.time_to_go or "value function horizon",
        "start_outside": args.start_outside,
        "start_margin": args.start_margin if args.start_outside else None,
        "path": "pettingzoo" if args.pettingzoo else "vector",
    }
    write_filter_results(rows, args.out, header)
    print(filter_table(rows))
    out = Path(args.out)
    print(f"\nwrote {out.with_suffix('.csv')}, {out.with_suffix('.json')}, {out.with_suffix('.md')}")
    print(f"wrote {plot_filter_tradeoff(rows, out.with_name(out.stem + '_tradeoff.png'), title=args.scene)}")
    if args.gif and loaded:
        # show episodes in which the nominal policy crashed (else the first three)
        picks = list(dict.fromkeys([*rows[0]["collided_episodes"][:3], 0, 1, 2]))[:3]
        starts = initial[picks] if initial is not None else None
        gif = record_side_by_side(
            scene,
            loaded[0].value_function,
            args.gif,
            thresholds[0],
            [args.seed + i for i in picks],
            ttg,
            scene_overrides=overrides,
            initial_states=starts,
        )
        print(f"wrote {gif} (left: nominal, right: filtered by {loaded[0].label})")
    return 0


def _parse_seeds(text: str) -> list[int]:
    """``"3"`` means seeds 0, 1, 2; ``"0,4,7"`` lists them."""
    try:
        if "," in text:
            return [int(s) for s in text.split(",") if s.strip()]
        count = int(text)
    except ValueError as err:
        raise ValueError(f"--seeds must be a count (3) or a list (0,4,7), got {text!r}") from err
    if count < 1:
        raise ValueError(f"--seeds must be at least 1, got {count}")
    return list(range(count))


def _parse_train_options(items: Sequence[str]) -> dict[str, object]:
    """``KEY=VALUE`` training options; values are read as JSON where they parse, else as strings."""
    import json

    options: dict[str, object] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--train expects KEY=VALUE, got {item!r}")
        try:
            options[key.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            options[key.replace("-", "_")] = value
    return options


def _cmd_sweep(args: argparse.Namespace) -> int:
    from sweeps.spec import AIR3D_LAYOUTS, NINE_D_LAYOUTS, SweepSpec
    from sweeps.sweep import run_sweep
    from training import parse_duration

    if args.layouts:
        layouts = [s.strip() for s in args.layouts.split(",") if s.strip()]
    else:
        layouts = list(AIR3D_LAYOUTS if args.system == "air3d" else NINE_D_LAYOUTS)
    spec = SweepSpec(
        system=args.system,
        layouts=layouts,
        seeds=_parse_seeds(args.seeds),
        budget_s=parse_duration(args.budget) if args.budget else (None if args.steps else 300.0),
        steps=args.steps,
        snapshots=args.snapshots,
        width=args.width,
        device=args.device,
        train=_parse_train_options(args.train),
        evaluation=args.evaluation,
        grid=args.grid,
        groundtruth=args.groundtruth,
        eval_time=args.eval_time,
        samples=args.samples,
        certify_samples=args.certify_samples,
        rollout_every=args.rollout_every,
        eval_seed=args.eval_seed,
        pairwise=args.pairwise,
    )
    if spec.budget_s is not None and spec.steps is not None:
        raise ValueError("give --budget or --steps, not both")
    report, failed = run_sweep(
        spec, args.out, backend=args.backend, workers=args.workers, threads=args.threads, address=args.address
    )
    print(f"report: {report}")
    if failed:
        print(f"reach sweep: {len(failed)} of {len(spec.tasks())} runs failed (listed in the report)", file=sys.stderr)
        return 1
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from safety.demo import run_demo
    from training.config import parse_duration

    report = run_demo(
        args.out,
        budget_s=parse_duration(args.budget),
        grid=args.grid,
        samples=args.samples,
        episodes=args.episodes,
        seed=args.seed,
    )
    print(f"report: {report}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="reach", description="Neural Hamilton-Jacobi reachability toolkit.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser("envs", help="list the registered environments and named scenes")
    p.set_defaults(func=_cmd_envs)

    p = sub.add_parser("record", help="run one episode and save it as a GIF")
    p.add_argument("env", nargs="?", default="Air3D-v0", help="Gymnasium id (default: Air3D-v0)")
    p.add_argument("--scene", default=None, help="named scene to run instead of the id's default")
    p.add_argument("--policy", choices=["straight", "random"], default="straight", help="agent policy")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--every", type=int, default=1, help="keep every N-th frame")
    p.add_argument("--out", default="episode.gif", help="GIF path")
    p.set_defaults(func=_cmd_record)

    p = sub.add_parser("groundtruth", help="solve a low-dimensional system's BRT on a grid (level-set method)")
    p.add_argument("system", help="system name, e.g. air3d")
    p.add_argument("--grid", default="101", help="nodes per dimension, e.g. 101 or 101,101,51")
    p.add_argument("--horizon", type=float, default=None, help="final time-to-go (default: the system's)")
    p.add_argument("--times", default="", help="comma-separated output times, e.g. 0.5,1.0,1.1")
    p.add_argument("--cfl", type=float, default=0.75)
    p.add_argument("--dissipation", choices=["local", "global"], default="local")
    p.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--compile", choices=["auto", "on", "off"], default="auto", help="torch.compile the solver step")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--plot", default=None, help="also draw zero-level slices to this PNG")
    p.set_defaults(func=_cmd_groundtruth)

    p = sub.add_parser("train", help="train a value network of any activation layout")
    p.add_argument("--system", default="air3d")
    p.add_argument("--layout", default="ssssl", help="one letter per activated layer (s, r, t) and a final l")
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--w0", type=float, default=30.0, help="sine frequency")
    p.add_argument("--parameterisation", choices=["exact", "vanilla"], default="exact")
    p.add_argument(
        "--sincos",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="encode headings as (sin, cos) (the default; --no-sincos: heading / pi, with a seam at +-pi)",
    )
    p.add_argument(
        "--sincos-radius",
        type=float,
        default=None,
        help="scale of the (sin, cos) inputs (default 1/pi: a turn spans as much input as the plain encoding)",
    )
    p.add_argument("--points", type=int, default=8192, help="points per step")
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--lr-final", type=float, default=1e-5)
    p.add_argument("--schedule", choices=["cosine", "constant"], default="cosine")
    p.add_argument("--loss", choices=["l1", "l2"], default="l1")
    p.add_argument(
        "--gradient-bound",
        type=_optional_float,
        default=None,
        help="penalise |dV/dx| above this many times l's steepest slope (normalised coordinates; removes "
        "cliffs; default 3, 'off' to disable)",
    )
    p.add_argument(
        "--gradient-weight", type=float, default=None, help="weight of the gradient-bound penalty (default 1)"
    )
    p.add_argument(
        "--gradients",
        choices=["fused", "autograd"],
        default="fused",
        help="input derivatives: carried through the layers by hand (one backward) or by autograd (double backward)",
    )
    p.add_argument(
        "--compile",
        choices=["auto", "on", "off"],
        default="auto",
        help="torch.compile the training step (auto: runs of 2 min or 2000 steps and more, eager if it fails)",
    )
    p.add_argument("--curriculum", type=float, default=0.5, help="share of the run over which t grows to T")
    p.add_argument("--pretrain", type=float, default=0.0, help="vanilla: share of the run on the boundary only")
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--budget", default=None, help="wall-clock budget, e.g. 90s, 10m, 1h")
    p.add_argument("--target-loss", type=float, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--log-every", type=int, default=25)
    p.add_argument("--checkpoint-every", type=float, default=30.0, help="seconds between checkpoints")
    p.add_argument("--groundtruth", default=None, help="grid solution .npz to evaluate against while training")
    p.add_argument("--eval-time", type=float, default=None, help="time for evaluation (default: last stored)")
    p.add_argument("--eval-every", type=float, default=60.0, help="seconds between evaluations")
    p.add_argument(
        "--tensorboard", action="store_true", help="also log metrics for TensorBoard in RUN/tensorboard"
    )
    p.add_argument(
        "--snapshots", type=int, default=0, help="save the network after every 1/N of the run (RUN/snapshots/)"
    )
    p.add_argument("--out", default=None, help="run directory for a new run")
    p.add_argument("--resume", default=None, metavar="RUN_DIR", help="continue the run in RUN_DIR")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser(
        "evaluate", help="verify value functions by rollouts: violations, delta-level, scenario guarantee"
    )
    p.add_argument("sources", nargs="+", help="run directories, checkpoints (.pt), DeepReach (.pth), grid (.npz)")
    p.add_argument("--samples", type=int, default=100_000, help="uniform states, the same for every model")
    p.add_argument(
        "--certify-samples", type=int, default=None, help="fresh states for eps (default: --samples; 0 skips)"
    )
    p.add_argument("--beta", type=float, default=1e-16, help="confidence parameter of the scenario guarantee")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dt", type=float, default=0.0025)
    p.add_argument("--integrator", choices=["euler", "rk4"], default="euler")
    p.add_argument(
        "--matmul-precision",
        choices=["float32", "bfloat16"],
        default="float32",
        help="bfloat16: networks' hidden products in bf16 during rollouts (faster, inexact; grids stay exact)",
    )
    p.add_argument("--horizon", type=float, default=None, help="time-to-go of the check (default: the system's)")
    p.add_argument("--chunk-size", type=int, default=16384)
    p.add_argument("--format", choices=["auto", "reach", "deepreach", "grid"], default="auto")
    p.add_argument("--system", default=None, help="system name (needed for DeepReach files)")
    p.add_argument("--layout", default=None, help="layout (needed for DeepReach files)")
    p.add_argument("--ground-truth", default=None, help="grid .npz to score IoU and MSE against")
    p.add_argument("--gt-time", type=float, default=None, help="time of that comparison (default: last stored)")
    p.add_argument(
        "--pairwise", default=None, help="two-car grid .npz (reach groundtruth relativepair): containment metric"
    )
    p.add_argument("--device", default="cpu")
    p.add_argument("--plot", action="store_true", help="also draw a bar chart of violation rates")
    p.add_argument("--out", default="results.csv", help="results path; .csv, .json and .md are written")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("plot", help="BRT slices, union-of-pairs overlays, violation bars or a filtered-episode GIF")
    p.add_argument("kind", choices=["slices", "union", "bars", "episode"])
    p.add_argument("sources", nargs="+", help="value functions (slices, episode) or a results .json (bars)")
    p.add_argument("--ground-truth", default=None, help="grid .npz drawn as the reference BRT (slices)")
    p.add_argument("--pairwise", default=None, help="two-car grid .npz whose union is overlaid (union)")
    p.add_argument(
        "--slice",
        action="append",
        default=None,
        help="slice 'name=value,...;axis1,axis2', e.g. 'x2=-0.4,th1=pi/2;x1,y1' (repeatable; default per system)",
    )
    p.add_argument("--t", type=float, default=None, help="time-to-go of the slices (default: the system's horizon)")
    p.add_argument("--format", choices=["auto", "reach", "deepreach", "grid"], default="auto")
    p.add_argument("--system", default=None)
    p.add_argument("--layout", default=None)
    p.add_argument("--scene", default="air3d", help="scene of the episode")
    p.add_argument("--threshold", type=float, default=None, help="filter threshold (default: 2 x rate bound x dt)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="PNG (slices, bars) or GIF (episode)")
    p.set_defaults(func=_cmd_plot)

    p = sub.add_parser(
        "filter-eval", help="episodes of a goal-seeking task with and without the safety filter: safety vs task"
    )
    p.add_argument("value_functions", nargs="*", help="value functions to filter with (runs, .pt, .pth, .npz)")
    p.add_argument("--scene", default="air3d", help="named scene (air3d, three-car-merge, three-car-crossing, ...)")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--thresholds", default=None, help="comma-separated filter thresholds (default: 2 x rate bound x dt)"
    )
    p.add_argument("--time-to-go", default=None, help="None (value function horizon), a number, or 'remaining'")
    p.add_argument("--pursuer", choices=["scene", "pursue", "random", "worst-case"], default="scene")
    p.add_argument("--adversary", default=None, help="value function whose d* the worst-case pursuer plays")
    p.add_argument("--start-outside", default=None, help="value function: start only from {V > margin}")
    p.add_argument("--start-margin", type=float, default=0.1)
    p.add_argument("--format", choices=["auto", "reach", "deepreach", "grid"], default="auto")
    p.add_argument("--layout", default=None, help="layout (needed for DeepReach files)")
    p.add_argument("--pettingzoo", action="store_true", help="run through the PettingZoo parallel env instead")
    p.add_argument("--gif", default=None, help="also write a side-by-side GIF (nominal | filtered) of 3 episodes")
    p.add_argument("--out", default="filter.csv", help="results path; .csv, .json and .md are written")
    p.set_defaults(func=_cmd_filter_eval)

    p = sub.add_parser(
        "sweep",
        help="train many layouts x seeds on a budget, score them along training, write a report (resumable)",
    )
    p.add_argument("--system", default="air3d")
    p.add_argument("--layouts", default=None, help="comma-separated (default: the seed paper's layouts)")
    p.add_argument("--seeds", default="3", help="a count (3 = seeds 0,1,2) or a list (0,4,7)")
    p.add_argument("--budget", default=None, help="training wall-clock budget per run, e.g. 90s, 5m (default 5m)")
    p.add_argument("--steps", type=int, default=None, help="train a fixed number of steps instead of a budget")
    p.add_argument("--snapshots", type=int, default=10, help="score each run after every 1/N of its budget")
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--train", action="append", default=[], metavar="KEY=VALUE", help="other reach train options, e.g. points=4096"
    )
    p.add_argument("--evaluation", choices=["auto", "groundtruth", "rollout"], default="auto")
    p.add_argument("--grid", type=int, default=101, help="ground-truth grid nodes per dimension (solved once)")
    p.add_argument("--groundtruth", default=None, help="an existing grid solution .npz to score against")
    p.add_argument("--eval-time", type=float, default=None, help="time to score at (default: the horizon)")
    p.add_argument("--samples", type=int, default=10_000, help="rollout evaluation: sampled states")
    p.add_argument("--certify-samples", type=int, default=None, help="rollout evaluation: fresh states (0: skip)")
    p.add_argument("--rollout-every", type=int, default=1, help="rollout evaluation: every k-th snapshot (+ last)")
    p.add_argument("--eval-seed", type=int, default=0)
    p.add_argument("--pairwise", default=None, help="rollout evaluation: two-car .npz for the union containment")
    p.add_argument("--backend", choices=["local", "ray"], default="local")
    p.add_argument("--address", default=None, help="ray: address of an existing cluster (default: start one)")
    p.add_argument("--workers", type=int, default=1, help="local: runs trained at once")
    p.add_argument("--threads", type=int, default=None, help="torch threads per run (local default: cores/workers)")
    p.add_argument("--out", required=True, help="sweep directory (an interrupted sweep continues there)")
    p.set_defaults(func=_cmd_sweep)

    p = sub.add_parser("demo", help="Air3D end to end: ground truth, training, verification, filter, report")
    p.add_argument("--out", default="reach-demo", help="report directory (an interrupted demo resumes)")
    p.add_argument("--budget", default="3m", help="training wall-clock budget, e.g. 90s, 3m")
    p.add_argument("--grid", type=int, default=101, help="ground-truth grid nodes per dimension")
    p.add_argument("--samples", type=int, default=10_000, help="verification rollouts per value function")
    p.add_argument("--episodes", type=int, default=500, help="filter-evaluation episodes per configuration")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_demo)

    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except ValueError as err:
        print(f"reach {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
