"""``snds train --init DIR``: refines the model in DIR with the demonstrations that
``--motion`` / ``--data`` name (:func:`snds.refine_run.refine_run`), saved, evaluated and
plotted as ``snds train`` does."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from snds.cli._common import check_config, data_source, summarise
from snds.errors import ConfigError
from snds.refine import RefineConfig
from snds.refine_run import refine_run

__all__ = ["add_arguments", "run_refinement"]

#: Beyond this reach (the training states' largest distance from the target, in trained
#: extents) the command says that the new demonstrations go where the policy decays faster.
REACH_NOTE = 1.05


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Adds ``--init`` to ``snds train``."""
    parser.add_argument(
        "--init",
        type=Path,
        metavar="DIR",
        default=None,
        help="refine the model in DIR: train from its weights, in about a second, on the "
        "demonstrations it was trained on (read again from what DIR/model.json records) and "
        "those --data / --motion name; its own settings with the short schedule of "
        "snds.refine.RefineConfig (--steps and the loss flags do not apply); --out default "
        "DIR-refined",
    )


def run_refinement(args: argparse.Namespace) -> int:
    """``snds train --init DIR``; ``--resume`` continues a refinement killed midway."""
    if args.se3:
        raise ConfigError("--init refines position models; --se3 does not apply")
    run = refine_run(
        args.init,
        data_source(args),
        args.out,
        config=RefineConfig(),
        check=check_config(args),
        plots=args.plot,
        resume=args.resume,
        checkpoint_every=args.checkpoint_every,
        progress=not args.quiet,
        threads=args.threads,
    )
    if not args.quiet:
        reach = run.config["refined_from"]["reach"]
        if reach > REACH_NOTE:
            print(
                f"snds: the added demonstrations reach {reach:.2f}x the trained extent, where "
                "the policy decays faster (decay_far): if they fit poorly, train from scratch",
                file=sys.stderr,
            )
        summarise(run.folder.path, run.metrics.to_dict())
    return 0
