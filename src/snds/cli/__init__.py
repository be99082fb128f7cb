"""The ``snds`` command line: a thin layer that builds configs and calls the library.

One module per subcommand (:mod:`snds.cli.train`, :mod:`~snds.cli.evaluate`,
:mod:`~snds.cli.plot`, :mod:`~snds.cli.benchmark`, :mod:`~snds.cli.simulate`,
:mod:`~snds.cli.export`, :mod:`~snds.cli.ros`, :mod:`~snds.cli.app`), each with
``register(commands)``, which adds its sub-parser, and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Callable, Sequence

import torch

from snds.cli import app, benchmark, evaluate, export, plot, ros, simulate, train, verify
from snds.cli.train import _policy_config
from snds.data.options import DataWarning
from snds.errors import SNDSError
from snds.run import RunWarning
from snds.threads import fastest_threads

__all__ = ["_build_parser", "_policy_config", "main"]

#: The subcommands, in the order ``snds --help`` lists them.
COMMANDS = (train, evaluate, plot, benchmark, simulate, export, verify, ros, app)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="snds", description="Globally stable neural motion policies from demonstrations."
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars or summaries")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch CPU threads (default: the library's choice for the work's size, "
        "snds.threads.fastest_threads; one for every size it runs, measured in "
        "benchmarks/results/threads.json)",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.register(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the command line; returns the exit code (2 for bad input)."""
    parser = _build_parser()
    args = parser.parse_args(argv)
    if args.threads is not None and args.threads < 1:
        parser.error("--threads must be >= 1")
    torch.set_num_threads(fastest_threads() if args.threads is None else args.threads)
    run: Callable[[argparse.Namespace], int] = args.run
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning(warnings.showwarning)
            if args.quiet:
                warnings.simplefilter("ignore", RunWarning)
            return run(args)
    except SNDSError as error:
        print(f"snds: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("snds: interrupted", file=sys.stderr)
        return 130


def _show_warning(fallback: Callable) -> Callable:
    """A :func:`warnings.showwarning` that prints a :class:`DataWarning` or a
    :class:`~snds.run.RunWarning` as one line ``snds: warning: ...``, and any other warning
    as ``fallback`` does."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, DataWarning | RunWarning):
            print(f"snds: warning: {message}", file=sys.stderr)
        else:
            fallback(message, category, filename, lineno, file, line)

    return show
