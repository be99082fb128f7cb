"""``snds app``: serves the draw-and-teach page (:mod:`snds.app`)."""

from __future__ import annotations

import argparse

from snds.errors import ConfigError

__all__ = ["register", "run"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds app`` to the subcommands."""
    parser = commands.add_parser(
        "app", help="a local web page: draw demonstrations, train, push the policy (snds[app])"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default: local only)")
    parser.add_argument("--port", type=int, default=8765, help="port (0: any free port)")
    parser.add_argument("--open", action="store_true", help="open the page in a web browser")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    try:
        from snds.app import serve
    except ImportError as error:
        raise ConfigError(
            f"snds app needs the app extra ({error.name} is missing): pip install 'snds[app]'"
        ) from None
    return serve(host=args.host, port=args.port, open_browser=args.open, quiet=args.quiet)
