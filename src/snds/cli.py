"""The ``snds`` command line: a thin layer that builds configs and calls the library."""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from snds.data import (
    MAX_END_SPREAD,
    Demonstrations,
    Normalization,
    Split,
    load_demonstrations,
    load_lasa,
    no_split,
    split_demos,
    split_samples,
)
from snds.errors import ConfigError, SNDSError
from snds.evaluate import evaluate
from snds.io import load_model, remove_temporaries, save_model, to_jsonable, write_json
from snds.policy import DEFAULT_WARP_LAYERS, Policy, PolicyConfig, StablePolicy
from snds.stability import ROLLOUTS, SAMPLES
from snds.train import CHECKPOINT, TrainConfig, TrainResult, fit

#: ``snds train --architecture`` choices: overrides of :class:`PolicyConfig`'s network sizes.
#: "compact" is for controllers that evaluate large batches (measured in benchmarks/README.md).
ARCHITECTURES: dict[str, dict[str, object]] = {
    "default": {},
    "compact": {"hidden": (64, 64), "fourier_features": 64},
}


#: ``snds train --shape-weight`` for SE(3) pose models (TrainConfig.shape_weight). Without it
#: a pose policy's 6-D V grows ill-conditioned off the one-curve data and the field stiff:
#: on Messy Snake lifted to SE(3), 0 of 1,000 random poses arrived within the horizon; with
#: it, 1,000 of 1,000 (benchmarks/README.md, "Higher dimensions and SE(3)").
POSE_SHAPE_WEIGHT = 0.01
#: ``snds train --position-noise`` for SE(3) pose models. The positions' default 0.0015 left
#: Messy Snake lifted to SE(3) converging from 0 of 1,000 random poses (1,000 without it).
POSE_POSITION_NOISE = 0.0


def _index_list(text: str) -> list[int]:
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated indices, got {text!r}"
        ) from None


def _demo_choice(text: str) -> int | list[int]:
    return _index_list(text) if "," in text else _index_list(text)[0]


def _push(text: str):
    from snds.sim import Push

    parts = text.split(",")
    try:
        step, *displacement = (float(part) for part in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected STEP,DX,DY,DZ (a step and metres), got {text!r}"
        ) from None
    if len(parts) != 4 or step != int(step) or step < 0:
        raise argparse.ArgumentTypeError(
            f"expected STEP,DX,DY,DZ with an integer step >= 0, got {text!r}"
        )
    return Push(step=int(step), displacement=tuple(displacement))


def _end_spread(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def _data_arguments(parser: argparse.ArgumentParser, *, required: bool) -> None:
    source = parser.add_mutually_exclusive_group(required=required)
    source.add_argument("--motion", help="a LASA handwriting motion, e.g. Sine")
    source.add_argument("--data", type=Path, help="demonstrations: .mat, .csv or .npz")
    parser.add_argument(
        "--demos",
        type=_demo_choice,
        default=None,
        help="K: the first K demonstrations; I,J,...: these demonstrations (0-based)",
    )
    parser.add_argument(
        "--max-end-spread",
        type=_end_spread,
        default=None,
        help="largest distance of a file's demonstration end from their common target, in "
        "extents (default 0.25; a model records the value it was trained with)",
    )


def _check_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--rollouts", type=int, default=ROLLOUTS, help="random starts of the stability check"
    )
    parser.add_argument(
        "--samples", type=int, default=SAMPLES, help="states of the decrease-condition check"
    )
    parser.add_argument(
        "--grid", action="store_true", help="stability rollouts from a grid, not random starts"
    )


def _obstacle_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--obstacle",
        action="append",
        default=[],
        metavar="SPEC",
        help="an obstacle (repeatable): sphere:CX,CY[,CZ],R, ellipsoid:CX,CY[,CZ],A1,A2[,A3] "
        "(semi-axes) or box:CX,CY[,CZ],H1,H2[,H3] (half-widths), then options margin=M, "
        "influence=D, angle=DEG (2-D) or angles=A/B/C (3-D), velocity=V1/V2[/V3]; "
        "docs/obstacles.md",
    )
    parser.add_argument(
        "--workspace",
        default=None,
        metavar="SPEC",
        help="box:CX,CY[,CZ],H1,H2[,H3][,margin=M]: the box the motion must stay in",
    )
    parser.add_argument(
        "--scene", type=Path, default=None, help="obstacles and workspace from a .json/.yaml file"
    )


def _scene(args: argparse.Namespace):
    """The obstacles of ``--scene``, ``--obstacle`` and ``--workspace``; None without any."""
    from snds.obstacles import Scene, load_scene, parse_obstacle, parse_workspace

    if not (args.obstacle or args.workspace or args.scene):
        return None
    base = load_scene(args.scene) if args.scene is not None else Scene()
    obstacles = base.obstacles + tuple(parse_obstacle(spec) for spec in args.obstacle)
    workspace = parse_workspace(args.workspace) if args.workspace else base.workspace
    return Scene(obstacles=obstacles, workspace=workspace)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="snds", description="Globally stable neural motion policies from demonstrations."
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars or summaries")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads (default 1: the networks are small, and one thread is "
        "faster than two on them, more so on a busy machine)",
    )
    commands = parser.add_subparsers(dest="command", required=True)

    train = commands.add_parser("train", help="train a stable policy and evaluate it")
    _data_arguments(train, required=True)
    train.add_argument("--seed", type=int, default=0, help="seed of weights and split")
    train.add_argument("--out", type=Path, default=None, help="model directory")
    train.add_argument("--plot", action="store_true", help="also write the plots")
    train.add_argument("--test-fraction", type=float, default=0.2, help="held-out samples")
    train.add_argument(
        "--test-demos",
        type=_index_list,
        default=None,
        help="hold out these whole demonstrations (I,J,...) instead of random samples",
    )
    train.add_argument("--steps", type=int, default=TrainConfig.steps, help="optimiser steps")
    train.add_argument("--window", type=int, default=TrainConfig.window, help="Euler window Nw")
    train.add_argument(
        "--velocity-loss", choices=["mse", "srvf"], default=TrainConfig.velocity_shape
    )
    train.add_argument(
        "--nominal-weight",
        type=float,
        default=TrainConfig.nominal_weight,
        help="weight of the velocity term on the nominal field before the projection, which "
        "keeps a fit from stalling where the projection hides f's gradient (0: the paper's "
        "loss)",
    )
    train.add_argument(
        "--position-noise",
        type=float,
        default=None,
        help="standard deviation of noise added to the training states (model coordinates, "
        "the data span about [-1, 1]), for demonstrations that run close together at "
        f"different speeds (default {TrainConfig.position_noise:g} for positions, "
        f"{POSE_POSITION_NOISE:g} for SE(3) pose models; 0: off)",
    )
    train.add_argument(
        "--shape-weight",
        type=float,
        default=None,
        help="weight of the penalty that keeps V's sublevel sets round off the data, against "
        f"stiff fields (default {POSE_SHAPE_WEIGHT:g} for SE(3) pose models, "
        f"{TrainConfig.shape_weight:g} (off) for positions)",
    )
    train.add_argument(
        "--decay-rate",
        type=float,
        default=PolicyConfig.decay_rate,
        help="rho in a(x) = rho V(x); 0 (with --decay-far 0 --decay-near 0) is the paper's "
        "relaxed mode (dV/dt <= 0 only)",
    )
    train.add_argument(
        "--decay-far",
        type=float,
        default=PolicyConfig.decay_far,
        help="extra decay rate per extent beyond the demonstrations' extent (0: off)",
    )
    train.add_argument(
        "--decay-near",
        type=float,
        default=PolicyConfig.decay_near,
        help="extra decay rate at the target, fading out at 0.2 of the extent (0: off)",
    )
    train.add_argument(
        "--warp-layers",
        type=int,
        default=PolicyConfig.warp_layers,
        help="coupling layers of a learned warp inside V, for demonstrations that wind back "
        f"and forth (default {DEFAULT_WARP_LAYERS} for positions of dimension >= 2, 0 in 1-D "
        "and for SE(3) poses; 0: off, V convex, ~3x faster training, see "
        "benchmarks/README.md)",
    )
    train.add_argument(
        "--warp-weight",
        type=float,
        default=TrainConfig.warp_weight,
        help="weight of the penalty that keeps the warp's Jacobian near the identity, against "
        f"stiff fields (default {TrainConfig.warp_weight:g}; 0: off)",
    )
    train.add_argument("--unconstrained", action="store_true", help="behavioural cloning")
    train.add_argument(
        "--architecture",
        choices=list(ARCHITECTURES),
        default="default",
        help="network sizes: default, or compact (hidden 64-64, 64 Fourier features: "
        "faster batches; measured in benchmarks/README.md)",
    )
    train.add_argument("--device", default="cpu", help="torch device (cpu, cuda, ...)")
    train.add_argument(
        "--resume",
        action="store_true",
        help="continue an interrupted run from OUT/checkpoint.safetensors (same arguments)",
    )
    train.add_argument(
        "--checkpoint-every", type=int, default=200, help="steps between checkpoints"
    )
    _check_arguments(train)
    train.add_argument(
        "--se3",
        action="store_true",
        help="learn a pose policy (position + orientation); automatic for pose files (CSV "
        "with columns qx,qy,qz,qw, NPZ with 'quat'); position data get synthetic orientations",
    )
    train.set_defaults(run=_train)

    evaluate_ = commands.add_parser("evaluate", help="evaluate a trained model")
    evaluate_.add_argument("model", type=Path, help="model directory")
    _data_arguments(evaluate_, required=False)
    evaluate_.add_argument("--seed", type=int, default=0, help="seed of the stability check")
    _check_arguments(evaluate_)
    _obstacle_arguments(evaluate_)
    evaluate_.set_defaults(run=_evaluate)

    plot = commands.add_parser("plot", help="plot a trained model")
    plot.add_argument("model", type=Path, help="model directory")
    _data_arguments(plot, required=False)
    plot.add_argument("--out", type=Path, default=None, help="folder of the PNGs")
    _obstacle_arguments(plot)
    plot.set_defaults(run=_plot)

    bench = commands.add_parser(
        "benchmark", help="train and evaluate methods x motions x seeds (resumable)"
    )
    bench.add_argument("--methods", default="snds,bc", help="comma-separated, e.g. snds,bc")
    bench.add_argument(
        "--motions", default="paper8", help="LASA names and/or groups: paper8, multi, all"
    )
    bench.add_argument("--demos", type=int, default=None, help="the first K demonstrations")
    bench.add_argument("--seeds", type=int, default=3, help="seeds 0 .. N-1")
    bench.add_argument("--jobs", type=int, default=None, help="local processes (default: cores)")
    bench.add_argument("--scheduler", default=None, help="Dask scheduler, e.g. tcp://host:8786")
    bench.add_argument("--out", type=Path, default=Path("runs/benchmark"), help="results folder")
    bench.add_argument("--steps", type=int, default=None, help="optimiser steps per run")
    bench.add_argument(
        "--batch-fits",
        type=int,
        default=1,
        metavar="K",
        help="fit up to K seeds of a motion at once as one stacked model (snds, bc)",
    )
    bench.add_argument(
        "--rollouts", type=int, default=None, help="random starts of each run's stability check"
    )
    bench.add_argument(
        "--samples", type=int, default=None, help="states of each run's decrease check"
    )
    bench.add_argument(
        "--quick", action="store_true", help="smaller stability check (100 rollouts, 5,000 samples)"
    )
    bench.set_defaults(run=_benchmark)

    from snds.sim import ROBOTS, SimConfig

    sim = commands.add_parser(
        "simulate", help="drive a simulated robot arm with a model (PyBullet, headless)"
    )
    sim.add_argument("model", type=Path, help="model directory")
    _data_arguments(sim, required=False)
    sim.add_argument("--robot", choices=list(ROBOTS), default=SimConfig.robot)
    sim.add_argument(
        "--push",
        type=_push,
        default=None,
        help="STEP,DX,DY,DZ: displace the end effector by (DX, DY, DZ) metres at control step STEP",
    )
    sim.add_argument(
        "--scale",
        type=float,
        default=None,
        help="metres per unit of the task's positions (default: fit the motion into the "
        "robot's reach)",
    )
    sim.add_argument(
        "--start-demo",
        type=int,
        default=0,
        help="start at this demonstration's first state (a pose model: its first pose)",
    )
    sim.add_argument(
        "--control-rate", type=float, default=SimConfig.control_rate, help="control loop, Hz"
    )
    sim.add_argument(
        "--time-limit", type=float, default=SimConfig.time_limit, help="seconds of simulation"
    )
    sim.add_argument(
        "--tolerance",
        type=float,
        default=SimConfig.tolerance,
        help="distance to the target (m) at which the run stops",
    )
    sim.add_argument(
        "--angle-tolerance",
        type=float,
        default=SimConfig.angle_tolerance,
        help="angle to the target orientation (rad) within which a pose model's run stops "
        "(with the distance within --tolerance)",
    )
    sim.add_argument(
        "--frames", type=int, default=6, help="rendered frames in frames.png (0: none)"
    )
    sim.add_argument(
        "--out", type=Path, default=None, help="results folder (default: MODEL/sim-ROBOT)"
    )
    _obstacle_arguments(sim)
    sim.set_defaults(run=_simulate)

    export = commands.add_parser(
        "export",
        help="export a model for a real-time controller (ONNX or torch.export); a pose "
        "model's file maps a pose (7 numbers) to a twist (6)",
    )
    export.add_argument("model", type=Path, help="model directory")
    export.add_argument("--format", choices=["onnx", "pt2"], default="onnx")
    export.add_argument(
        "--dtype",
        choices=["float32", "float64"],
        default="float32",
        help="precision of the exported graph",
    )
    export.add_argument(
        "--out", type=Path, default=None, help="file (default: MODEL/policy.onnx or .pt2)"
    )
    export.add_argument(
        "--samples", type=int, default=10_000, help="random states of the equality check"
    )
    export.add_argument("--seed", type=int, default=0, help="seed of those states")
    _obstacle_arguments(export)
    export.set_defaults(run=_export)

    app = commands.add_parser(
        "app", help="a local web page: draw demonstrations, train, push the policy (snds[app])"
    )
    app.add_argument("--host", default="127.0.0.1", help="address to bind (default: local only)")
    app.add_argument("--port", type=int, default=8765, help="port (0: any free port)")
    app.add_argument("--open", action="store_true", help="open the page in a web browser")
    app.set_defaults(run=_app)
    return parser


def _load_data(
    motion: str | None,
    data: Path | None,
    demos: int | list[int] | None,
    max_end_spread: float | None = None,
) -> Demonstrations:
    spread = MAX_END_SPREAD if max_end_spread is None else max_end_spread
    if motion is None and demos is not None:
        # Selected before the target is chosen: a file may end at several places.
        select = list(range(demos)) if isinstance(demos, int) else demos
        return load_demonstrations(data, select=select, max_end_spread=spread)
    if motion is not None:
        loaded = load_lasa(motion)
    else:
        loaded = load_demonstrations(data, max_end_spread=spread)
    if demos is None:
        return loaded
    return loaded.first(demos) if isinstance(demos, int) else loaded.select(demos)


def _make_split(demos: Demonstrations, record: dict) -> Split:
    """The split described by a ``split`` record of model.json."""
    if record.get("test_demos"):
        return split_demos(demos, test_demos=record["test_demos"])
    fraction = float(record.get("test_fraction", 0.0))
    if fraction <= 0:
        return no_split(demos)
    return split_samples(demos, test_fraction=fraction, seed=int(record.get("seed", 0)))


def _source(args: argparse.Namespace) -> dict:
    if args.motion is not None:
        return {"motion": args.motion, "demos": args.demos}
    spread = MAX_END_SPREAD if args.max_end_spread is None else args.max_end_spread
    return {"file": str(Path(args.data).resolve()), "demos": args.demos, "max_end_spread": spread}


def _check_sizes(args: argparse.Namespace) -> None:
    """Refuses stability-check sizes that would fail only after training, before any work."""
    if args.rollouts < 1:
        raise ConfigError(f"--rollouts must be >= 1, got {args.rollouts}")
    if args.samples < 0:
        raise ConfigError(f"--samples must be >= 0, got {args.samples}")


def _train_settings(
    args: argparse.Namespace,
    *,
    shape_weight: float = TrainConfig.shape_weight,
    position_noise: float = TrainConfig.position_noise,
) -> tuple[dict, TrainConfig]:
    """The split record and the optimisation settings of ``snds train``'s arguments;
    ``shape_weight`` and ``position_noise`` are the defaults of their flags for this kind of
    model."""
    split_record = {
        "test_fraction": args.test_fraction,
        "seed": args.seed,
        "test_demos": args.test_demos,
    }
    train_config = TrainConfig(
        steps=args.steps,
        window=args.window,
        velocity_shape=args.velocity_loss,
        nominal_weight=args.nominal_weight,
        position_noise=position_noise if args.position_noise is None else args.position_noise,
        shape_weight=shape_weight if args.shape_weight is None else args.shape_weight,
        warp_weight=args.warp_weight,
        seed=args.seed,
        device=args.device,
    )
    return split_record, train_config


def _save_run(
    out: Path, policy: Policy, result: TrainResult, *, data: dict, split: dict, train: TrainConfig
) -> None:
    """Writes a trained model with the record of how it was trained, and its loss history."""
    # The file is written from a CPU copy: the policy stays on its device (--device) for the
    # stability check that follows.
    if policy.center.device.type != "cpu":
        policy = copy.deepcopy(policy).to("cpu")
    # Results of an earlier run must not sit beside the new model if this one is killed.
    for name in ("metrics.json", "loss.json"):
        (out / name).unlink(missing_ok=True)
    record = {
        "data": data,
        "split": split,
        "train": train.to_dict(),
        "train_result": {k: v for k, v in dataclasses.asdict(result).items() if k != "history"},
    }
    save_model(policy, out, extra=record)
    write_json(out / "loss.json", {"history": result.history})


def _policy_config(args: argparse.Namespace) -> PolicyConfig:
    """The architecture that ``snds train``'s flags ask for, for positions and poses alike."""
    return PolicyConfig(
        **ARCHITECTURES[args.architecture],
        decay_rate=args.decay_rate,
        decay_far=args.decay_far,
        decay_near=args.decay_near,
        warp_layers=args.warp_layers,
        stable=not args.unconstrained,
    )


def _train(args: argparse.Namespace) -> int:
    _check_sizes(args)
    if args.se3 or (args.data is not None and _is_pose_file(args.data)):
        if args.resume:
            # Refused rather than ignored: a user must not believe a pose run resumed.
            raise ConfigError("--resume is not available for SE(3) training yet")
        return _train_se3(args)
    demos = _load_data(args.motion, args.data, args.demos, args.max_end_spread)
    out = args.out or Path("runs") / (demos.name or Path(str(args.data)).stem)
    split_record, train_config = _train_settings(args)
    split = _make_split(demos, split_record)
    policy = StablePolicy(
        dim=demos.dim,
        normalization=Normalization.fit(demos),
        config=_policy_config(args),
        seed=args.seed,
    )
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a directory")
    remove_temporaries(out)
    checkpoint = out / CHECKPOINT
    if not args.resume:
        checkpoint.unlink(missing_ok=True)
    elif not checkpoint.is_file() and not args.quiet:
        print(f"snds: no checkpoint in {out}: training from the start", file=sys.stderr)
    result = fit(
        policy,
        demos,
        split,
        train_config,
        progress=not args.quiet,
        checkpoint=checkpoint,
        checkpoint_every=args.checkpoint_every,
    )
    _save_run(out, policy, result, data=_source(args), split=split_record, train=train_config)
    metrics = evaluate(
        policy,
        demos,
        split,
        seed=args.seed,
        rollouts=args.rollouts,
        grid=args.grid,
        samples=args.samples,
    )
    metrics["train_seconds"] = result.seconds
    write_json(out / "metrics.json", to_jsonable(metrics))
    if args.plot:
        _write_plots(policy.to("cpu"), demos, out, result.history)
    # Only now is the run complete: until here a kill leaves the checkpoint to resume from.
    checkpoint.unlink(missing_ok=True)
    if not args.quiet:
        _summarise(out, metrics)
    return 0


def _model_and_data(args: argparse.Namespace) -> tuple[StablePolicy, dict, Demonstrations]:
    policy, description = load_model(args.model)
    if args.motion is None and args.data is None:
        source = description.get("data", {})
        if "motion" in source:
            demos = _load_data(source["motion"], None, source.get("demos"))
        elif "file" in source:
            demos = _load_data(
                None, Path(source["file"]), source.get("demos"), source.get("max_end_spread")
            )
        else:
            raise SNDSError(f"{args.model}: no data recorded; pass --motion or --data")
    else:
        demos = _load_data(args.motion, args.data, args.demos, args.max_end_spread)
    if demos.dim != policy.dim:
        raise SNDSError(
            f"the data has dimension {demos.dim}, the model in {args.model} {policy.dim}"
        )
    return policy, description, demos


def _evaluate(args: argparse.Namespace) -> int:
    scene = _scene(args)
    _check_sizes(args)
    if _is_pose_model(args.model):
        if scene is not None:
            raise ConfigError("obstacles: snds evaluate takes position models (simulate: both)")
        return _evaluate_se3(args)
    policy, description, demos = _model_and_data(args)
    if scene is not None:
        return _evaluate_obstacles(args, policy, demos, scene)
    metrics = evaluate(
        policy,
        demos,
        _make_split(demos, description.get("split", {})),
        seed=args.seed,
        rollouts=args.rollouts,
        grid=args.grid,
        samples=args.samples,
    )
    metrics["train_seconds"] = description.get("train_result", {}).get("seconds")
    write_json(args.model / "metrics.json", to_jsonable(metrics))
    if not args.quiet:
        _summarise(args.model, metrics)
    return 0


def _evaluate_obstacles(args: argparse.Namespace, policy: Policy, demos: Demonstrations, scene):
    """``snds evaluate`` with obstacles: the stability report under them, ``obstacles.json``."""
    from snds.obstacles import check_obstacles

    scene.check(demos.dim, demos.target)
    report = check_obstacles(policy, demos, scene, rollouts=args.rollouts, seed=args.seed)
    write_json(args.model / "obstacles.json", to_jsonable(report.to_dict()))
    if not args.quiet:
        r, d = report.random, report.demos
        print(
            f"{args.model / 'obstacles.json'}: {len(scene.obstacles)} obstacles"
            + (" and a workspace" if scene.workspace is not None else "")
            + "; random free "
            f"starts: {r.reached} of {r.starts} reached, {r.stalled} stalled, {r.penetrated} "
            f"penetrated, min clearance {r.min_clearance:.4g} (margin {r.margin:.4g}); demo "
            f"starts: {d.reached} of {d.starts} reached, {d.penetrated} penetrated; "
            f"{report.wall_seconds:.1f} s"
        )
    return 0


def _plot(args: argparse.Namespace) -> int:
    scene = _scene(args)
    if _is_pose_model(args.model):
        if scene is not None:
            raise ConfigError("obstacles: snds plot takes position models (simulate: both)")
        return _plot_se3(args)
    policy, _, demos = _model_and_data(args)
    if scene is not None:
        scene.check(demos.dim, demos.target)
    history = None
    loss_file = args.model / "loss.json"
    if loss_file.is_file():
        history = json.loads(loss_file.read_text()).get("history")
    paths = _write_plots(policy, demos, args.out or args.model, history, scene=scene)
    if not args.quiet:
        for path in paths:
            print(path)
    return 0


def _benchmark(args: argparse.Namespace) -> int:
    from snds import benchmark

    tasks = benchmark.make_tasks(
        benchmark.resolve_motions(args.motions),
        benchmark.resolve_methods(args.methods),
        seeds=args.seeds,
        demos=args.demos,
    )
    base = (
        benchmark.SweepSettings.quick(steps=args.steps)
        if args.quick
        else benchmark.SweepSettings(steps=args.steps)
    )
    settings = benchmark.SweepSettings(
        steps=args.steps,
        rollouts=base.rollouts if args.rollouts is None else args.rollouts,
        samples=base.samples if args.samples is None else args.samples,
        batch_fits=args.batch_fits,
    )
    rows = benchmark.run_sweep(
        tasks,
        out=args.out,
        settings=settings,
        jobs=args.jobs,
        scheduler=args.scheduler,
        progress=not args.quiet,
    )
    benchmark.plot_benchmark(rows, args.out)
    if not args.quiet:
        print((args.out / "summary.md").read_text(), end="")
    return 0


def _simulate(args: argparse.Namespace) -> int:
    import numpy as np

    from snds.sim import SimConfig, simulate
    from snds.sim.plots import plot_frames, plot_path, render_frames

    scene = _scene(args)
    pose = _is_pose_model(args.model)
    policy, _, demos = _pose_model_and_data(args) if pose else _model_and_data(args)
    if not 0 <= args.start_demo < len(demos):
        raise SNDSError(f"--start-demo {args.start_demo}: there are {len(demos)} demonstrations")
    if scene is not None:
        scene.check(3 if pose else demos.dim, demos.target_position if pose else demos.target)
    config = SimConfig(
        robot=args.robot,
        scale=args.scale,
        control_rate=args.control_rate,
        time_limit=args.time_limit,
        tolerance=args.tolerance,
        angle_tolerance=args.angle_tolerance,
        push=args.push,
        obstacles=scene,
    )
    first = demos[args.start_demo]
    # A pose model starts from a pose: position and quaternion, 7 numbers.
    start = np.r_[first.positions[0], first.orientations[0]] if pose else first.positions[0]
    result = simulate(policy, start, config)
    out = args.out or args.model / f"sim-{config.robot}"
    record = {
        "model": str(Path(args.model).resolve()),
        "data": _source(args) if args.motion or args.data else None,
        "start_demo": args.start_demo,
        **result.to_dict(),
    }
    write_json(out / "sim.json", to_jsonable(record))
    paths = [plot_path(result, demos, out / "path.png")]
    if args.frames > 0:
        frames, steps = render_frames(result, demos, count=args.frames)
        paths.append(plot_frames(result, frames, steps, out / "frames.png"))
    if not args.quiet:
        outcome = (
            f"reached the target in {result.times[-1]:.2f} s"
            if result.reached
            else f"did not reach the target in {result.times[-1]:.2f} s"
        )
        line = f"{out}: {outcome}, final error {1000 * result.final_error:.2f} mm"
        if result.drives_orientation:
            line += f" and {result.final_orientation_error:.4f} rad"
        if result.push_time is not None:
            recovery = (
                "never recovered"
                if result.recovery_time is None
                else f"recovered in {result.recovery_time:.2f} s"
            )
            line += f"; pushed at {result.push_time:.2f} s, {recovery}"
        print(line)
    return 0


def _export(args: argparse.Namespace) -> int:
    from snds import export

    scene = _scene(args)
    policy, _ = load_model(args.model)
    if scene is not None:
        policy = _with_obstacles(policy, scene)
    out = args.out or args.model / f"policy.{args.format}"
    dtype = getattr(torch, args.dtype)
    path = export.FORMATS[args.format](policy, out, dtype=dtype)
    check = export.verify(path, policy, samples=args.samples, seed=args.seed)
    write_json(path.with_name(path.name + ".check.json"), to_jsonable(check.to_dict()))
    if not check.passed:
        # A controller must not pick up a model that computes something else.
        path.unlink(missing_ok=True)
        raise export.ExportError(
            f"{path}: outputs differ from the library's by {check.max_error:.2e} "
            f"(relative), more than {check.tolerance:.0e}, and by {check.max_error_float64:.2e} "
            f"from the exact (float64) policy, where the library in {check.dtype} is "
            f"{check.library_error:.2e} from it"
        )
    if not args.quiet:
        print(
            f"{path}: {export.signature(policy).description}; {check.samples} random "
            f"states, largest difference from the library {check.max_error:.2e} (relative; "
            f"{check.max_abs_diff:.2e} absolute)"
        )
    return 0


def _with_obstacles(policy: Policy, scene) -> Policy:
    """The policy of ``snds export --obstacle``: the modulation in the graph (fixed obstacles,
    position models), or a one-line refusal of what the graph cannot hold."""
    from snds.obstacles import ModulatedPolicy
    from snds.se3 import PosePolicy

    if isinstance(policy, PosePolicy):
        raise ConfigError(
            "obstacles cannot be exported with a pose model (its graph maps poses to twists); "
            "modulate the linear part in the controller (snds.obstacles.modulate_twist)"
        )
    if scene.moving:
        raise ConfigError(
            "moving obstacles (velocity=) cannot be exported: the graph has no time input"
        )
    scene.check(policy.dim, policy.normalization.center)
    return ModulatedPolicy(policy, scene)


def _app(args: argparse.Namespace) -> int:
    try:
        from snds.app import serve
    except ImportError as error:
        raise ConfigError(
            f"snds app needs the app extra ({error.name} is missing): pip install 'snds[app]'"
        ) from None
    return serve(host=args.host, port=args.port, open_browser=args.open, quiet=args.quiet)


def _write_plots(
    policy: StablePolicy,
    demos: Demonstrations,
    out: Path,
    history: list[float] | None,
    scene=None,
) -> list[Path]:
    from snds.plotting import plot_all

    policy = policy.to(torch.float64).eval()
    if scene is not None:
        from snds.plotting import plot_obstacles

        return [plot_obstacles(policy, demos, scene, out / "obstacles.png")]
    return plot_all(policy, demos, out, history=history)


def _summarise(out: Path, metrics: dict) -> None:
    stability = metrics["stability"]
    seconds = metrics.get("train_seconds")
    timing = f"trained in {seconds:.1f} s, " if seconds is not None else ""
    print(
        f"{out}: {timing}velocity MSE {metrics['velocity_mse_paper']:.4f} (paper scale), "
        f"DTW {metrics['dtw_paper']:.4f} (paper scale), "
        f"converged {stability['converged_fraction']:.3f} of {stability['rollouts']} rollouts, "
        f"{stability['decrease_violations']} decrease violations in "
        f"{stability['samples_checked']} samples" + _guard_summary(stability)
    )


def _guard_summary(stability: dict) -> str:
    if stability.get("integrator") != "guarded euler":
        return ""
    return (
        f"; largest safe Euler step {stability['largest_safe_dt']:.3g} s "
        f"(data: {stability['dt']:.3g} s), guard shortened steps in "
        f"{stability['shortened_fraction']:.0%} of rollouts"
    )


# --- SE(3) pose policies (snds.se3) ------------------------------------------------------------


def _is_pose_file(path: Path) -> bool:
    from snds.data.poses import is_pose_file

    return is_pose_file(path)


def _is_pose_model(directory: Path) -> bool:
    from snds.io import read_description

    return read_description(directory).get("kind") == "se3"


def _pose_data(
    motion: str | None, data: Path | None, demos, seed: int, max_end_spread: float | None = None
):
    """Pose demonstrations: a pose file as it is, or position data (LASA, .mat, ...) lifted
    with synthetic orientations seeded by ``seed`` (see
    :func:`snds.data.poses.with_synthetic_orientations`)."""
    from snds.data.poses import load_poses, with_synthetic_orientations

    if data is not None and _is_pose_file(data):
        select = list(range(demos)) if isinstance(demos, int) else demos
        spread = MAX_END_SPREAD if max_end_spread is None else max_end_spread
        return load_poses(data, select=select, max_end_spread=spread)
    loaded = _load_data(motion, data, demos, max_end_spread)
    return with_synthetic_orientations(loaded, seed=seed)


def _train_se3(args: argparse.Namespace) -> int:
    from snds.se3 import evaluate_pose, make_pose_policy

    poses = _pose_data(args.motion, args.data, args.demos, args.seed, args.max_end_spread)
    out = args.out or Path("runs") / f"{poses.name or Path(str(args.data)).stem}-se3"
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a directory")
    policy, demos = make_pose_policy(poses, config=_policy_config(args), seed=args.seed)
    split_record, train_config = _train_settings(
        args, shape_weight=POSE_SHAPE_WEIGHT, position_noise=POSE_POSITION_NOISE
    )
    split = _make_split(demos, split_record)
    result = fit(policy, demos, split, train_config, progress=not args.quiet)
    source = {**_source(args), "orientation_seed": args.seed}
    _save_run(out, policy, result, data=source, split=split_record, train=train_config)
    metrics = evaluate_pose(
        policy, poses, split, seed=args.seed, rollouts=args.rollouts, samples=args.samples
    )
    metrics["train_seconds"] = result.seconds
    write_json(out / "metrics.json", to_jsonable(metrics))
    if args.plot:
        from snds.se3 import plot_pose_policy

        plot_pose_policy(policy, poses, out, history=result.history)
    if not args.quiet:
        _summarise_se3(out, metrics)
    return 0


def _pose_model_and_data(args: argparse.Namespace):
    policy, description = load_model(args.model)
    source = description.get("data", {})
    seed = int(source.get("orientation_seed", 0))
    if args.motion is not None or args.data is not None:
        poses = _pose_data(args.motion, args.data, args.demos, seed, args.max_end_spread)
    elif "motion" in source or "file" in source:
        data = Path(source["file"]) if "file" in source else None
        spread = source.get("max_end_spread")
        poses = _pose_data(source.get("motion"), data, source.get("demos"), seed, spread)
    else:
        raise SNDSError(f"{args.model}: no data recorded; pass --motion or --data")
    return policy, description, poses


def _evaluate_se3(args: argparse.Namespace) -> int:
    from snds.se3 import evaluate_pose, tangent_demonstrations

    policy, description, poses = _pose_model_and_data(args)
    tangent = tangent_demonstrations(
        poses,
        position_scale=policy.config.position_scale,
        rotation_scale=policy.config.rotation_scale,
    )
    split = _make_split(tangent, description.get("split", {}))
    metrics = evaluate_pose(
        policy, poses, split, seed=args.seed, rollouts=args.rollouts, samples=args.samples
    )
    metrics["train_seconds"] = description.get("train_result", {}).get("seconds")
    write_json(args.model / "metrics.json", to_jsonable(metrics))
    if not args.quiet:
        _summarise_se3(args.model, metrics)
    return 0


def _plot_se3(args: argparse.Namespace) -> int:
    from snds.se3 import plot_pose_policy

    policy, _, poses = _pose_model_and_data(args)
    loss_file = args.model / "loss.json"
    history = json.loads(loss_file.read_text()).get("history") if loss_file.is_file() else None
    paths = plot_pose_policy(policy, poses, args.out or args.model, history=history)
    if not args.quiet:
        for path in paths:
            print(path)
    return 0


def _summarise_se3(out: Path, metrics: dict) -> None:
    stability = metrics["stability"]
    seconds = metrics.get("train_seconds")
    timing = f"trained in {seconds:.1f} s, " if seconds is not None else ""
    print(
        f"{out}: {timing}position DTW {metrics['position_dtw_paper']:.4f} (paper scale), "
        f"orientation error {metrics['orientation_error_along']:.4f} rad along the path, "
        f"{metrics['final_orientation_error']:.4f} rad at the end; converged "
        f"{stability['converged_fraction']:.3f} of {stability['rollouts']} random poses, "
        f"{stability['decrease_violations']} decrease violations in "
        f"{stability['samples_checked']} samples"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the command line; returns the exit code (2 for bad input)."""
    parser = _build_parser()
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error("--threads must be >= 1")
    torch.set_num_threads(args.threads)
    run: Callable[[argparse.Namespace], int] = args.run
    try:
        return run(args)
    except SNDSError as error:
        print(f"snds: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("snds: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
