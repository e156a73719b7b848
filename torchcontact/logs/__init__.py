"""Processing robot logs: the Parquet log format, streamed estimation, simulation, import, plots.

Optional dependencies: the ``logs`` extra (pyarrow, tqdm, matplotlib, rosbags); ``ray`` for
``engine="ray"``. The public names below are imported lazily (PEP 562), so that the command line
registers its log commands without importing torch or pyarrow.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

# public name -> module it lives in (one per line)
_LAZY = {
    "LogConstraints": "torchcontact.logs.chunks",
    "LogError": "torchcontact.errors",
    "LogEstimator": "torchcontact.logs.chunks",
    "LogLocalize": "torchcontact.logs.chunks",
    "estimate_file": "torchcontact.logs.pipeline",
    "estimate_files": "torchcontact.logs.pipeline",
    "expand_inputs": "torchcontact.logs.format",
    "input_schema": "torchcontact.logs.format",
    "joint_names_of": "torchcontact.logs.format",
    "savgol_derivatives": "torchcontact.logs.derive",
    "simulated_table": "torchcontact.logs.simlog",
    "write_simulated_log": "torchcontact.logs.simlog",
}

__all__ = [
    "LogConstraints",
    "LogError",
    "LogEstimator",
    "LogLocalize",
    "estimate_file",
    "estimate_files",
    "expand_inputs",
    "input_schema",
    "joint_names_of",
    "savgol_derivatives",
    "simulated_table",
    "write_simulated_log",
]

if TYPE_CHECKING:  # pragma: no cover - static analysers see the eager imports
    from torchcontact.errors import LogError
    from torchcontact.logs.chunks import LogConstraints, LogEstimator, LogLocalize
    from torchcontact.logs.derive import savgol_derivatives
    from torchcontact.logs.format import expand_inputs, input_schema, joint_names_of
    from torchcontact.logs.pipeline import estimate_file, estimate_files
    from torchcontact.logs.simlog import simulated_table, write_simulated_log


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'torchcontact.logs' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value  # cache: later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
