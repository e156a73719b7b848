"""The library's exceptions: one base class, :class:`TorchContactError`, and a subclass per concern.

Every error torchcontact raises on purpose derives from :class:`TorchContactError`, so an
application (and the CLI, which prints one ``error:`` line for these and a traceback only with
``--debug``) can tell a user error from a bug. Each subclass also derives from the builtin a caller
would have caught before this module existed (``ValueError`` for bad input, ``RuntimeError`` for a
failing device or build), so ``except ValueError`` keeps working.

This module imports nothing heavy: :mod:`torchcontact.runtime` uses it without torch.
"""

from __future__ import annotations

__all__ = [
    "CheckpointError",
    "ConvertError",
    "FTConnectionError",
    "FTError",
    "InputError",
    "KernelBuildError",
    "LogError",
    "MissingExtraError",
    "ModelMismatchError",
    "OutputBusyError",
    "ProfileError",
    "TorchContactError",
    "URDFError",
]


class TorchContactError(Exception):
    """Base class of every error torchcontact raises on purpose.

    Attributes:
        exit_code: the process exit status the CLI uses for it: 2 for a usage error (a bad
            option or argument), 1 for bad data (a malformed file, a failed device).
    """

    exit_code: int = 1


class InputError(TorchContactError, ValueError):
    """An argument of the wrong shape, dtype, device or value; the message names the argument."""

    exit_code = 2


class URDFError(TorchContactError, ValueError):
    """A URDF that cannot describe a robot torchcontact can model; the message names the element."""


class LogError(TorchContactError, ValueError):
    """A log that cannot be processed (not Parquet, wrong joints, no sensor column, ...)."""


class ConvertError(LogError):
    """An input that cannot be converted (the message names the file and what is missing)."""


class CheckpointError(TorchContactError, ValueError):
    """A missing, tampered, foreign or inconsistent checkpoint; the message says why."""


class ModelMismatchError(TorchContactError, ValueError):
    """An exported graph or checkpoint that does not fit the robot, sensors or layout expected."""


class ProfileError(TorchContactError, ValueError):
    """A sensor profile file is missing, malformed, or names an unknown key or value."""


class FTError(TorchContactError, RuntimeError):
    """Base class of F/T driver errors."""


class FTConnectionError(FTError):
    """The port or host cannot be opened."""


class KernelBuildError(TorchContactError, RuntimeError):
    """A generated kernel could not be compiled or loaded (callers fall back to eager torch)."""


class MissingExtraError(TorchContactError, ImportError):
    """An optional dependency is not installed; the message names the extra that brings it.

    Example:
        >>> raise MissingExtraError("trimesh", "meshes")
        Traceback (most recent call last):
        ...
        torchcontact.errors.MissingExtraError: this needs the package 'trimesh': pip install ...
    """

    def __init__(self, package: str, extra: str) -> None:
        super().__init__(f"this needs the package {package!r}: pip install 'torchcontact[{extra}]'")
        self.package = package
        self.extra = extra


class OutputBusyError(TorchContactError, RuntimeError):
    """Another live process holds the output's lock (``OUT.lock``): the message names it."""
