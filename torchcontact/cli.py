"""The ``torchcontact`` command line.

Each concern registers its own sub-commands through an ``add_parser(subparsers)`` function, so
that this module only wires them together; the residual-learning and export applications
(``torchcontact train``, ``torchcontact export``, installed as :mod:`torchcontact.apps.training`
and :mod:`torchcontact.apps.export`) bring their own parsers and are imported only when run.

Every user error is one ``error:`` line on stderr and exit code 2 (usage: a bad option or
argument) or 1 (data: a malformed file, a failed device); ``--debug`` adds the traceback.
Warnings are ``warning:`` lines. Help texts show the defaults.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback
import warnings
from collections.abc import Callable, Sequence
from typing import Any

from torchcontact.errors import TorchContactError

__all__ = ["Parser", "build_parser", "guarded", "main"]

#: Applications run by ``torchcontact <name> ...``: module (installed name, source-tree name), help.
APPS: dict[str, tuple[str, str, str]] = {
    "train": (
        "torchcontact.apps.training.__main__",
        "training.__main__",
        "learn an F/T residual model (fit) or compare corrections (benchmark)",
    ),
    "export": (
        "torchcontact.apps.export.__main__",
        "export.__main__",
        "write ONNX graphs: the contact estimator, or a learned residual",
    ),
}


class _HelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to an option's help when it has a default worth showing."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "(default" in text or action.required or action.default in (None, False):
            return text
        if action.default is argparse.SUPPRESS or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """``argparse`` parser of every torchcontact command.

    Help texts show defaults, every (sub)command accepts ``--debug``, and a usage error is one
    ``error:`` line with exit code 2.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)
        self.add_argument(
            "--debug",
            action="store_true",
            default=argparse.SUPPRESS,
            help="show the traceback of an error",
        )

    def error(self, message: str) -> Any:  # noqa: D102 - argparse's hook
        print(f"error: {self.prog}: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def guarded(run: Callable[[], int | None], debug: bool = False) -> int:
    """Run a command: library errors become one ``error:`` line and an exit code.

    Args:
        run: the command.
        debug: print tracebacks too.

    Returns:
        The command's exit code, or the error's: :attr:`TorchContactError.exit_code` (2 usage,
        1 data), 1 for an operating-system error (a missing file, no space), 130 when
        interrupted.
    """

    def show(msg: str) -> None:
        if debug:
            traceback.print_exc()
        print(f"error: {_one_line(msg)}", file=sys.stderr)

    def warn(message: Any, category: Any, *_: Any, **__: Any) -> None:
        print(f"warning: {_one_line(message)}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.showwarning = warn
        try:
            return int(run() or 0)
        except TorchContactError as exc:
            show(str(exc))
            return exc.exit_code
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130
        except OSError as exc:
            where = f"{exc.filename}: " if exc.filename else ""
            show(f"{where}{exc.strerror or exc}")
            return 1
        except Exception as exc:  # a bug: say so, one line unless --debug
            show(
                f"unexpected {type(exc).__name__}: {exc} (please report it; --debug shows the"
                " traceback)"
            )
            return 1


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level argument parser with every sub-command registered."""
    from torchcontact.drivers import cli as drivers_cli
    from torchcontact.logs import cli as logs_cli
    from torchcontact.view import cli as view_cli

    parser = Parser(prog="torchcontact", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    logs_cli.add_parser(sub)
    view_cli.add_parser(sub)
    drivers_cli.add_parser(sub)
    for name, (_, _, help_text) in APPS.items():
        sub.add_parser(name, help=help_text, add_help=False)  # parsed by the application
    return parser


def app_module(name: str) -> Any:
    """The ``__main__`` module of an application (``train``, ``export``).

    Installed, it is ``torchcontact.apps.<name>``; in a source tree without an install, the
    top-level folder of that name.
    """
    installed, source, _ = APPS[name]
    try:
        return importlib.import_module(installed)
    except ModuleNotFoundError as exc:
        if exc.name is None or not installed.startswith(exc.name):
            raise
        return importlib.import_module(source)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    first = next((a for a in argv if a != "--debug"), None)
    if first in APPS:
        rest = list(argv)
        rest.remove(first)
        return guarded(lambda: app_module(first).main(rest, prog=f"torchcontact {first}"), debug)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from torchcontact import __version__

        print(__version__)
        return 0
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    return guarded(lambda: args.func(args), debug)


if __name__ == "__main__":
    sys.exit(main())
