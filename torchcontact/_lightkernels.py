"""The kernel cache's standard-library modules, without the kernels package (which imports torch).

:mod:`torchcontact.kernels._store` (the cache: entries, checks, detached builds) and
:mod:`torchcontact.kernels._csource` (the C++ text, the tape VM's source and entry) import the
standard library only. This module loads them by path for a command that should not pay for
torch: ``torchcontact cache`` reads the store; ``torchcontact estimate`` starts the tape VM's
build (:func:`start_vm_build`) before it imports torch, so that the compiler runs on a core the
import leaves idle instead of being waited for at the first program (a first run on an empty
cache). The kernels package adopts that build (:func:`vm_build`): one compiler, never two.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

#: Batches at least this large start a background build under ``backend="auto"``, and run on the
#: tape VM meanwhile (:data:`torchcontact.kernels.AUTO_BUILD_MIN_FRAMES`, defined here so that a
#: command can tell before importing torch whether its run will need the VM).
AUTO_BUILD_MIN_FRAMES = 2048

#: Detached VM builds started here: entry name -> the builder process.
_builds: dict[str, subprocess.Popen] = {}


def kernel_module(name: str) -> Any:
    """``torchcontact.kernels.<name>`` (``_store`` or ``_csource``), without the package.

    The package's module when the package is imported, else the file loaded by path (once,
    under a private name).
    """
    full = f"torchcontact.kernels.{name}"
    if full in sys.modules:
        return sys.modules[full]
    private = f"_torchcontact_kernel{name}"
    if private in sys.modules:
        return sys.modules[private]
    spec = importlib.util.spec_from_file_location(
        private, Path(__file__).parent / "kernels" / f"{name}.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[private] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def start_vm_build(dtype: str = "double") -> bool:
    """Start building the tape VM for ``dtype`` (``"double"``/``"float"``) when the cache has none.

    A detached builder (:func:`torchcontact.kernels._store.spawn_build`), as the kernels package
    starts it; nothing when the VM is built already, when its entry is damaged (the package
    heals it, with its warning), when ``$TORCHCONTACT_VM`` is ``0``, or when the cache cannot be
    written (the package reports that at its first program). Never raises.

    Returns:
        True when a build was started here.
    """
    cs = kernel_module("_csource")
    if os.environ.get(cs.VM_ENV, "").strip().lower() == "0" or dtype not in ("double", "float"):
        return False
    try:
        store = kernel_module("_store")
        entry, src = cs.vm_entry(store, dtype)
        if entry.check()[0] != "absent":
            return False
        proc = _builds.get(entry.name)
        if proc is not None and proc.poll() is None:
            return False
        store.write_source(entry.source, src)
        _builds[entry.name] = store.spawn_build(entry)
    except OSError:  # an unwritable cache: the package reports it at its first program
        return False
    return True


def vm_build(entry_name: str) -> subprocess.Popen | None:
    """The builder :func:`start_vm_build` started for this VM entry, or None."""
    return _builds.get(entry_name)
