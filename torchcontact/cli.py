"""The ``torchcontact`` command line.

Each concern registers its own sub-commands through an ``add_parser(subparsers)`` function, so
that this module only wires them together.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from torchcontact.drivers import cli as drivers_cli
from torchcontact.logs import cli as logs_cli


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level argument parser with every sub-command registered."""
    parser = argparse.ArgumentParser(prog="torchcontact", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    drivers_cli.add_parser(sub)
    logs_cli.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit code."""
    from torchcontact import __version__

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        print(__version__)
        return 0
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
