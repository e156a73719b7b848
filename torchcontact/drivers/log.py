"""Parquet logs of F/T frames in the project's log format.

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
        import pyarrow as pa

        self.path = Path(path)
        self.column = f"ft.{sensor}"
        self.schema = pa.schema([("t_ns", pa.int64()), (self.column, pa.list_(pa.float64(), 6))])
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
        import pyarrow.parquet as pq

        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = pq.ParquetWriter(self.path, self.schema)
        if not self._t:
            return
        values = pa.array(np.concatenate(self._w), type=pa.float64())
        table = pa.table(
            {
                "t_ns": pa.array(self._t, type=pa.int64()),
                self.column: pa.FixedSizeListArray.from_arrays(values, 6),
            },
            schema=self.schema,
        )
        self._writer.write_table(table)
        self.rows += len(self._t)
        self._t, self._w = [], []

    def close(self) -> None:
        """Flush and close the file (an empty log still gets its schema)."""
        self.flush()
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> FTLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_ft_log(path: str | Path, sensor: str) -> tuple[np.ndarray, np.ndarray]:
    """Read a log written by :class:`FTLogWriter`.

    Returns:
        ``t_ns`` (N,) int64 and wrenches (N, 6) float64 [force; moment], N and N m.

    Raises:
        ValueError: If the columns are missing or not in the log format.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    column = f"ft.{sensor}"
    if "t_ns" not in table.column_names or column not in table.column_names:
        raise ValueError(f"{path}: need columns t_ns and {column}; found {table.column_names}")
    ftype = table.schema.field(column).type
    if not (pa.types.is_fixed_size_list(ftype) and ftype.list_size == 6):
        raise ValueError(f"{path}: {column} is {ftype}, expected fixed_size_list<double>[6]")
    t = table.column("t_ns").to_numpy().astype(np.int64)
    w = np.asarray(table.column(column).combine_chunks().flatten(), dtype=np.float64)
    return t, w.reshape(-1, 6)
