"""The ``torchcontact`` command line.

Each concern registers its own sub-commands through an ``add_parser(subparsers)`` function, so
that this module only wires them together; the residual-learning and export applications
(``torchcontact train``, ``torchcontact export``, installed as :mod:`torchcontact.apps.training`
and :mod:`torchcontact.apps.export`) bring their own parsers and are imported only when run.
Start-up is lazy: a command imports only the module that registers it (:data:`COMMANDS`), and
that module imports torch, pyarrow and the rest inside the command, so ``torchcontact --help``
imports neither torch nor numpy, and ``estimate`` none of ray, matplotlib, onnx, rosbags or
pymodbus.

Every user error is one ``error:`` line on stderr and exit code 2 (usage: a bad option or
argument) or 1 (data: a malformed file, a failed device); ``--debug`` adds the traceback.
Warnings are ``warning:`` lines. Help texts show the defaults.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from typing import Any

from torchcontact.errors import TorchContactError

__all__ = ["COMMANDS", "Parser", "build_parser", "console_main", "guarded", "main"]

#: Sub-commands: the module whose ``add_parser`` registers them, and their line in the help.
COMMANDS: dict[str, tuple[str, str]] = {
    "estimate": ("torchcontact.logs.cli", "estimate contacts of every frame of logs"),
    "simulate": ("torchcontact.logs.cli", "write a simulated log with known contacts"),
    "demo": ("torchcontact.logs.cli", "simulate -> estimate -> plot into a folder"),
    "plot": ("torchcontact.logs.cli", "PNG plots of an estimated log"),
    "convert": ("torchcontact.logs.cli", "ROS 1/2 bag (sqlite3, MCAP) or CSV -> log"),
    "view": (
        "torchcontact.view.cli",
        "interactive 3D timeline of a log and its estimate (rerun .rrd, extra 'view')",
    ),
    "sensor": ("torchcontact.drivers.cli", "F/T sensor drivers and simulator"),
    "run": ("torchcontact.drivers.cli", "live loop: sensor + joints -> estimator -> JSON"),
}

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


#: Optional dependencies -> the extra that installs them (pyproject.toml), for the error a
#: command gives when one is missing.
EXTRA_OF = {
    "pyarrow": "logs",
    "tqdm": "logs",
    "matplotlib": "logs",
    "rosbags": "logs",
    "ray": "ray",
    "pymodbus": "drivers",
    "serial": "drivers",
    "onnx": "export",
    "onnxruntime": "export",
    "safetensors": "train",
}


class _HelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to an option's help when it has a default worth showing."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        # identity, not ==: a default of 0 or 0.0 is worth showing, and 0 == False
        unset = action.default is None or action.default is False
        if "(default" in text or action.required or unset or not action.option_strings:
            return text
        if action.default is argparse.SUPPRESS:
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
        1 data), 1 for an operating-system error (a missing file, no space) or a missing
        optional dependency (the message names the extra that installs it), 130 when
        interrupted.
    """

    def show(msg: str) -> None:
        if debug:
            import traceback

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
            missing = getattr(exc, "name", None) if isinstance(exc, ModuleNotFoundError) else None
            extra = EXTRA_OF.get((missing or "").split(".")[0])
            if extra is not None:  # an optional dependency: the extra that brings it
                show(
                    f"this command needs {missing}, which is not installed: pip install"
                    f" 'torchcontact[{extra}]'"
                )
                return 1
            show(
                f"unexpected {type(exc).__name__}: {exc} (please report it; --debug shows the"
                " traceback)"
            )
            return 1


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Build the top-level argument parser.

    Args:
        command: the sub-command about to run: only the module that registers it is imported
            (None: none; ``"*"``: every module, e.g. to list every option). The other commands
            appear in the help with their line from :data:`COMMANDS`.
    """
    parser = Parser(
        prog="torchcontact",
        description="torchcontact: contact forces from F/T sensors and tactile skin; every job is"
        " a command (torchcontact COMMAND --help)",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = [m for name, (m, _) in COMMANDS.items() if command in (name, "*")]
    for module in dict.fromkeys(wanted):
        importlib.import_module(module).add_parser(sub)
    for name, (_, help_text) in COMMANDS.items():
        if name not in sub.choices:  # listed only: registered when it runs
            sub.add_parser(name, help=help_text, add_help=False)
    add_cache_parser(sub)  # argparse only: always registered
    for name, (_, _, help_text) in APPS.items():
        sub.add_parser(name, help=help_text, add_help=False)  # parsed by the application
    return parser


def add_cache_parser(sub: Any) -> None:
    """``torchcontact cache info|clear``: the kernel cache (:mod:`torchcontact.kernels._store`).

    Registered here without importing the kernels (they import torch); the command imports them
    when it runs.
    """
    p = sub.add_parser(
        "cache",
        help="show (info) or empty (clear) the kernel cache",
        description="The generated-kernel cache: its location, entries (state, sizes) and compile"
        " bound (info), or remove its entries (clear; entries being built are kept).",
    )
    p.add_argument("action", choices=("info", "clear"), help="info: show it; clear: empty it")
    p.add_argument("--json", action="store_true", help="print info or the summary as JSON")
    p.set_defaults(func=_cache_command)


def _kernel_store() -> Any:
    """:mod:`torchcontact.kernels._store` without the kernels package (which imports torch)."""
    from torchcontact._lightkernels import kernel_module

    return kernel_module("_store")


def _cache_command(args: argparse.Namespace) -> int:
    import json

    _store = _kernel_store()
    root = _store.cache_dir() / "kernels"
    if args.action == "info":
        data = _store.info(root)
        print(json.dumps(data, indent=1) if args.json else _store.format_info(data))
        return 0
    res = _store.clear(root)
    if args.json:
        print(json.dumps(res))
    else:
        busy = f"; kept {len(res['busy'])} being built" if res["busy"] else ""
        print(f"removed {res['removed']} kernels ({res['bytes'] / 1e6:.1f} MB) from {root}{busy}")
    return 0


def _background_builds() -> list[str]:
    """The kernel builds going on now (none when no kernel module is loaded yet)."""
    kernels = sys.modules.get("torchcontact.kernels")  # never imported here for this
    return kernels.background_builds() if kernels is not None else []


def _background_note(before: list[str]) -> None:
    """One ``note:`` line when kernel builds this command started go on after it.

    Args:
        before: :func:`_background_builds` when the command started (a process running
            several commands, as a test does, names only each command's own).
    """
    kernels = sys.modules.get("torchcontact.kernels")
    note = kernels.background_note(before) if kernels is not None else None
    if note:
        print(note, file=sys.stderr)


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
    before = _background_builds()
    if first in APPS:
        rest = list(argv)
        rest.remove(first)
        rc = guarded(lambda: app_module(first).main(rest, prog=f"torchcontact {first}"), debug)
        _background_note(before)
        return rc
    parser = build_parser(first)
    args = parser.parse_args(argv)
    if args.version:
        from torchcontact import __version__

        print(__version__)
        return 0
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    rc = guarded(lambda: args.func(args), debug)
    _background_note(before)
    return rc


def _exit_code(exc: SystemExit) -> int:
    """The process exit code of a ``SystemExit`` (as the interpreter computes it)."""
    if exc.code is None:
        return 0
    if isinstance(exc.code, int):
        return exc.code
    print(exc.code, file=sys.stderr)
    return 1


def _finish_process() -> None:
    """What the interpreter's shutdown would do that a command's result still needs.

    Outputs are published (atomically) before a command returns, its threads joined and its
    files closed; what is left is buffered in this process: the standard streams and the
    ``logging`` handlers, and rerun's recordings (its own exit handler sends what they still
    buffer). A Ray instance this process started is shut down as Ray's own exit handler would
    (its head processes and workers end with it); a running cluster it joined ends the driver's
    job when the process exits, as for any driver that ends. Kernel builds this command
    started are detached processes: they go on (:func:`_background_note` said so); those
    deferred to the process's end (the tape VM ran their programs) start here, as the
    interpreter's exit handler would start them.
    """
    kernels = sys.modules.get("torchcontact.kernels")  # never imported here for this
    if kernels is not None:
        kernels.start_deferred_builds()
    _end_ray()
    rerun = sys.modules.get("rerun")  # its exit handler sends what recordings still buffer
    if rerun is not None and hasattr(rerun, "rerun_shutdown"):
        rerun.rerun_shutdown()
    logging = sys.modules.get("logging")  # imported by a command, or nothing to flush
    if logging is not None:
        logging.shutdown()


def _end_ray() -> None:
    """Shut down the Ray instance this process started (never imports Ray).

    A running cluster the process joined (``RAY_ADDRESS``) is left to end the driver's job as
    the process exits, as for any driver that ends: its shutdown took 0.3 s of every run.
    """
    ray = sys.modules.get("ray")
    boot = sys.modules.get("torchcontact.logs._ray_boot")
    if ray is not None and getattr(ray, "is_initialized", lambda: False)():
        if boot is None or boot.started_local_instance():
            ray.shutdown()


def _stream_error(exc: OSError, rc: int) -> int:
    """The exit code after standard output failed.

    A closed pipe (``| head``) keeps ``rc``; anything else (a full disk) is one ``error:`` line
    and exit 1, never a silent 0.
    """
    if isinstance(exc, BrokenPipeError):
        return rc
    with contextlib.suppress(OSError):
        print(f"error: standard output: {exc.strerror or exc}", file=sys.stderr, flush=True)
    return rc or 1


def console_main() -> None:
    """The ``torchcontact`` console script: :func:`main`, then end the process at once.

    The interpreter's shutdown (joining idle pool threads, tearing down torch, pyarrow and every
    module) cost 2.5-10 s after the output was published on a loaded 2-core machine
    (``benchmarks/exit_delay.py``, docs/pipeline.md). Once the command has returned, the
    streams are flushed and logging is shut down, the process ends with :func:`os._exit`.
    In-process callers (tests, scripts, ``python -m torchcontact``) use :func:`main`, which
    returns the exit code.
    """
    try:
        rc = main()
    except SystemExit as exc:  # --help, --version, a usage error
        rc = _exit_code(exc)
    except KeyboardInterrupt:  # outside guarded(): while parsing or importing
        print("interrupted", file=sys.stderr)
        rc = 130
    except OSError as exc:  # outside guarded(): writing --help or --version
        rc = _stream_error(exc, 0)
    try:
        _finish_process()
    except Exception as exc:  # never lose the exit code to a teardown hook
        print(f"warning: at exit: {type(exc).__name__}: {_one_line(exc)}", file=sys.stderr)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except OSError as exc:
            rc = _stream_error(exc, rc) if stream is sys.stdout else rc or 1
    os._exit(rc)


if __name__ == "__main__":
    sys.exit(main())
