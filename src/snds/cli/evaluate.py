"""``snds evaluate``: the accuracy and the stability check of a saved model."""

from __future__ import annotations

import argparse
from pathlib import Path

from snds.cli._args import check_arguments, data_arguments, obstacle_arguments
from snds.cli._common import (
    check_config,
    model_and_data,
    refuse_obstacles,
    scene_of,
    summarise,
)
from snds.data import Demonstrations
from snds.evaluate import evaluate
from snds.io import to_jsonable, write_json
from snds.obstacles import check_obstacles
from snds.policy import Policy
from snds.run import split_of
from snds.runs import RunFolder

__all__ = ["register", "run"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds evaluate`` to the subcommands."""
    parser = commands.add_parser("evaluate", help="evaluate a trained model")
    parser.add_argument("model", type=Path, help="model directory")
    data_arguments(parser, required=False)
    parser.add_argument("--seed", type=int, default=0, help="seed of the stability check")
    check_arguments(parser)
    obstacle_arguments(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    scene = scene_of(args)
    check = check_config(args)
    policy, description, demos = model_and_data(args)
    if scene is not None:
        refuse_obstacles(policy, "evaluate")
        return _evaluate_obstacles(args, policy, demos, scene)
    split = split_of(demos, description.get("split", {}))
    metrics = evaluate(policy, demos, split, check=check).to_dict()
    metrics["train_seconds"] = description.get("train_result", {}).get("seconds")
    RunFolder(args.model).write_metrics(metrics)
    if not args.quiet:
        summarise(args.model, metrics)
    return 0


def _evaluate_obstacles(args: argparse.Namespace, policy: Policy, demos: Demonstrations, scene):
    """``snds evaluate`` with obstacles: the stability report under them, ``obstacles.json``."""
    scene.check(demos.dim, demos.target)
    report = check_obstacles(policy, demos, scene, config=check_config(args))
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
