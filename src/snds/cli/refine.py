"""``snds train --init DIR``: refines the model in DIR with the demonstrations that
``--motion`` / ``--data`` name (:func:`snds.refine.refine_model`), then saves, evaluates and
plots it as ``snds train`` does."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from snds.cli._common import _check_config, _data_source, _summarise, _write_plots
from snds.errors import ConfigError
from snds.refine import RefineConfig, refine_model
from snds.runs import RunFolder

__all__ = ["add_arguments", "run_refinement"]


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
        "snds.refine.RefineConfig (--steps and the loss flags do not apply)",
    )


def run_refinement(args: argparse.Namespace, *, evaluate: Callable[..., dict]) -> int:
    """``snds train --init DIR``: the refined model goes to ``--out`` (default DIR-refined);
    ``--resume`` continues a refinement killed midway from its checkpoint.

    Arguments:
        args: ``snds train``'s arguments.
        evaluate: :func:`snds.evaluate.evaluate`, or what ``snds train`` evaluates with.
    """
    init = Path(args.init)
    if args.se3:
        raise ConfigError("--init refines position models; --se3 does not apply")
    check = _check_config(args)
    source = _data_source(args)
    new = source.load()
    out = args.out or init.parent / f"{init.name}-refined"
    folder = RunFolder(out)
    folder.prepare(resume=args.resume)
    refined = refine_model(
        init,
        new,
        out,
        added=source.record(),
        config=RefineConfig(),
        progress=not args.quiet,
        checkpoint_every=args.checkpoint_every,
    )
    result = refined.refinement.result
    folder.save(refined.policy, result, record=refined.record)
    metrics = evaluate(refined.policy, refined.demos, refined.split, check=check)
    metrics["train_seconds"] = result.seconds
    folder.write_metrics(metrics)
    if args.plot:
        _write_plots(refined.policy.to("cpu"), refined.demos, out, result.history)
    # Only now is the refinement complete: until here a kill leaves the checkpoint.
    folder.finish()
    if not args.quiet:
        reach = refined.refinement.reach
        if reach > 1.05:
            print(
                f"snds: the added demonstrations reach {reach:.2f}x the trained extent, where "
                "the policy decays faster (decay_far): if they fit poorly, train from scratch",
                file=sys.stderr,
            )
        _summarise(out, metrics)
    return 0
