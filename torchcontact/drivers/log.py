"""Parquet logs of F/T frames in the project's log format.

Written and read through :mod:`torchcontact.logs.format` (page checksums, atomic rename).
One row per frame: ``t_ns`` (int64, host monotonic ns) and ``ft.<sensor>`` (fixed-size list of
6 float64, [force; moment] in N and N m, sensor frame).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


class FTLogWriter:
    """Append F/T frames to a Parquet file, writing a row group every ``batch`` rows.

    Args:
        path: Output file.
        sensor: Sensor name; the column is ``ft.<sensor>``.
        batch: Rows per row group.

    Example:
        >>> import tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "log.parquet")
        >>> with FTLogWriter(path, "ft300") as log:
        ...     log.append(1, np.arange(6.0))
        >>> read_ft_log(path, "ft300")[1].shape
        (1, 6)
    """

    def __init__(self, path: str | Path, sensor: str, batch: int = 1000) -> None:
        from torchcontact.logs.format import ft_column, ft_log_schema

        self.path = Path(path)
        self.column = ft_column(sensor)
        self.schema = ft_log_schema(sensor)
        self.batch = batch
        self._t: list[int] = []
        self._w: list[np.ndarray] = []
        self._writer: Any = None
        self.rows = 0

    def append(self, t_ns: int, wrench: np.ndarray) -> None:
        """Add one frame: ``t_ns`` int ns, ``wrench`` (6,) N and N m."""
        self._t.append(int(t_ns))
        self._w.append(np.asarray(wrench, dtype=np.float64).reshape(6))
        if len(self._t) >= self.batch:
            self.flush()

    def flush(self) -> None:
        """Write buffered rows."""
        import pyarrow as pa

        from torchcontact.logs.format import LogWriter, fixed_list

        if self._writer is None:
            self._writer = LogWriter(self.path, self.schema)
        if not self._t:
            return
        table = pa.table(
            {
                "t_ns": pa.array(self._t, type=pa.int64()),
                self.column: fixed_list(np.stack(self._w)),
            },
            schema=self.schema,
        )
        self._writer.write(table)
        self.rows += len(self._t)
        self._t, self._w = [], []

    def close(self) -> None:
        """Flush and close the file (an empty log still gets its schema).

        The file is written as ``<path>.tmp`` and renamed to ``path`` here.
        """
        self.flush()
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> FTLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_ft_log(path: str | Path, sensor: str) -> tuple[np.ndarray, np.ndarray]:
    """Read a log written by :class:`FTLogWriter` (or any log with that sensor's column).

    Returns:
        ``t_ns`` (N,) int64 and wrenches (N, 6) float64 [force; moment], N and N m.

    Raises:
        LogError: the file is not a readable log or lacks ``t_ns`` or ``ft.<sensor>``.
    """
    from torchcontact.logs.format import ft_column, read_log_columns

    cols = read_log_columns(path, ["t_ns", ft_column(sensor)])
    return cols["t_ns"], cols[ft_column(sensor)]
