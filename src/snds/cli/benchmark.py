"""``snds benchmark``: a resumable sweep of methods x motions x seeds (:mod:`snds.benchmark`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from snds import benchmark

__all__ = ["register", "run"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds benchmark`` to the subcommands."""
    parser = commands.add_parser(
        "benchmark", help="train and evaluate methods x motions x seeds (resumable)"
    )
    parser.add_argument("--methods", default="snds,bc", help="comma-separated, e.g. snds,bc")
    parser.add_argument(
        "--motions",
        default="paper8",
        help="LASA names, groups (paper8, multi, all) and/or demonstrations files (.mat, .csv, "
        ".npz; a pose file is an SE(3) task)",
    )
    parser.add_argument(
        "--se3",
        action="store_true",
        help="pose tasks: position data get synthetic orientations (methods: snds, bc)",
    )
    parser.add_argument("--demos", type=int, default=None, help="the first K demonstrations")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0 .. N-1")
    parser.add_argument("--jobs", type=int, default=None, help="local processes (default: cores)")
    parser.add_argument("--scheduler", default=None, help="Dask scheduler, e.g. tcp://host:8786")
    parser.add_argument("--out", type=Path, default=Path("runs/benchmark"), help="results folder")
    parser.add_argument("--steps", type=int, default=None, help="optimiser steps per run")
    parser.add_argument(
        "--batch-fits",
        type=int,
        default=1,
        metavar="K",
        help="fit up to K seeds of a motion at once as one stacked model (snds, bc)",
    )
    parser.add_argument(
        "--rollouts", type=int, default=None, help="random starts of each run's stability check"
    )
    parser.add_argument(
        "--samples", type=int, default=None, help="states of each run's decrease check"
    )
    parser.add_argument(
        "--quick", action="store_true", help="smaller stability check (100 rollouts, 5,000 samples)"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    tasks = benchmark.make_tasks(
        benchmark.resolve_motions(args.motions),
        benchmark.resolve_methods(args.methods),
        seeds=args.seeds,
        demos=args.demos,
        se3=args.se3,
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
