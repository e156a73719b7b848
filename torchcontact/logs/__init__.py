"""Processing robot logs: the Parquet log format, streamed estimation, simulation, import, plots.

Optional dependencies: the ``logs`` extra (pyarrow, tqdm, matplotlib, rosbags); ``ray`` for
``engine="ray"``.
"""

from torchcontact.logs.derive import savgol_derivatives
from torchcontact.logs.format import input_schema, joint_names_of
from torchcontact.logs.pipeline import (
    LogConstraints,
    LogError,
    LogEstimator,
    estimate_file,
    estimate_files,
    expand_inputs,
)
from torchcontact.logs.simlog import simulated_table, write_simulated_log

__all__ = [
    "LogConstraints",
    "LogError",
    "LogEstimator",
    "estimate_file",
    "estimate_files",
    "expand_inputs",
    "input_schema",
    "joint_names_of",
    "savgol_derivatives",
    "simulated_table",
    "write_simulated_log",
]
