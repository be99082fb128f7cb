"""``snds plot``: the plots of a saved model."""

from __future__ import annotations

import argparse
from pathlib import Path

from snds.cli._args import data_arguments, obstacle_arguments
from snds.cli._common import model_and_data, refuse_obstacles, scene_of, write_plots
from snds.runs import RunFolder

__all__ = ["register", "run"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds plot`` to the subcommands."""
    parser = commands.add_parser("plot", help="plot a trained model")
    parser.add_argument("model", type=Path, help="model directory")
    data_arguments(parser, required=False)
    parser.add_argument("--out", type=Path, default=None, help="folder of the PNGs")
    obstacle_arguments(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    scene = scene_of(args)
    policy, _, demos = model_and_data(args)
    if scene is not None:
        refuse_obstacles(policy, "plot")
        scene.check(demos.dim, demos.target)
    history = RunFolder(args.model).read_history()
    paths = write_plots(policy, demos, args.out or args.model, history, scene=scene)
    if not args.quiet:
        for path in paths:
            print(path)
    return 0
