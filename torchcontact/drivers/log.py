"""Parquet logs of F/T frames in the project's log format.

Written and read through :mod:`torchcontact.logs.format` (page checksums, atomic rename).
One row per frame: ``t_ns`` (int64, host monotonic ns) and per sensor ``ft.<sensor>``
(fixed-size list of 6 float64, [force; moment] in N and N m, sensor frame). ``torchcontact run``
on a step with online inputs adds the bias state of each frame (null where the frame has no
estimate), per sensor:

- ``bias.<sensor>``: 6 float64, the offset subtracted from the reading [N; N m];
- ``bias_std.<sensor>``: 6 float64, its standard deviation;
- ``bias_since_update.<sensor>``: float64, s since the last update (null before the first);
- ``bias_updated.<sensor>``: bool, this frame updated it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np


class FTLogWriter:
    """Append F/T frames to a Parquet file, writing a row group every ``batch`` rows.

    Args:
        path: Output file.
        sensor: Sensor name, or the names of the sensors of each row's ``(6 S,)`` reading (a
            :class:`~torchcontact.drivers.live.SensorGroup`); the columns are ``ft.<sensor>``.
        batch: Rows per row group.
        bias: Add the bias columns (see the module).
        profile: The driver profile of the sensors (name or TOML path), recorded in the schema
            metadata ``torchcontact.ft_profiles`` (:mod:`torchcontact.logs.noise` takes the
            readings' noise from its datasheet ``[noise]``), or None.

    Example:
        >>> import tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "log.parquet")
        >>> with FTLogWriter(path, "ft300") as log:
        ...     log.append(1, np.arange(6.0))
        >>> read_ft_log(path, "ft300")[1].shape
        (1, 6)
    """

    def __init__(
        self,
        path: str | Path,
        sensor: str | Sequence[str],
        batch: int = 1000,
        bias: bool = False,
        profile: str | Path | None = None,
    ) -> None:
        import json

        import pyarrow as pa

        from torchcontact.logs.format import (
            BIAS_COLUMNS,
            META_FT_PROFILES,
            bias_column,
            ft_column,
            ft_log_schema,
        )

        self.path = Path(path)
        self.sensors = [sensor] if isinstance(sensor, str) else list(sensor)
        self.columns = [ft_column(s) for s in self.sensors]
        self.column = self.columns[0]
        fields = list(ft_log_schema(self.sensors[0]))
        fields += [pa.field(c, pa.list_(pa.float64(), 6)) for c in self.columns[1:]]
        self.bias = bool(bias)
        if self.bias:
            types = {"list": pa.list_(pa.float64(), 6), "float64": pa.float64(), "bool": pa.bool_()}
            for s in self.sensors:
                for prefix, (_, kind, _) in BIAS_COLUMNS.items():
                    fields.append(pa.field(bias_column(prefix, s), types[kind]))
        meta = None
        if profile is not None:  # estimate weighs the readings by the profile's datasheet noise
            name = str(Path(profile).resolve()) if str(profile).endswith(".toml") else str(profile)
            meta = {META_FT_PROFILES: json.dumps({s: name for s in self.sensors})}
        self.schema = pa.schema(fields, metadata=meta)
        self.batch = batch
        self._t: list[int] = []
        self._w: list[np.ndarray] = []
        self._b: list[Mapping[str, Any] | None] = []
        self._writer: Any = None
        self.rows = 0

    def append(
        self, t_ns: int, wrench: np.ndarray, bias: Mapping[str, Mapping[str, Any]] | None = None
    ) -> None:
        """Add one frame.

        Args:
            t_ns: int ns.
            wrench: ``(6 S,)`` N and N m, the sensors in order.
            bias: per sensor its bias record (``offset``, ``std``, ``since_update``,
                ``updated``: ``BiasState.as_dict`` of :mod:`torchcontact.online.bias`), or None
                (nulls).
        """
        self._t.append(int(t_ns))
        self._w.append(np.asarray(wrench, dtype=np.float64).reshape(len(self.sensors), 6))
        self._b.append(bias)
        if len(self._t) >= self.batch:
            self.flush()

    def flush(self) -> None:
        """Write buffered rows."""
        import pyarrow as pa

        from torchcontact.logs.format import BIAS_COLUMNS, LogWriter, bias_column, fixed_list

        if self._writer is None:
            self._writer = LogWriter(self.path, self.schema)
        if not self._t:
            return
        w = np.stack(self._w)
        cols: dict[str, Any] = {"t_ns": pa.array(self._t, type=pa.int64())}
        for i, c in enumerate(self.columns):
            cols[c] = fixed_list(w[:, i])
        if self.bias:
            for s in self.sensors:
                for prefix, (key, _, _) in BIAS_COLUMNS.items():
                    vals = [None if b is None or s not in b else b[s][key] for b in self._b]
                    name = bias_column(prefix, s)
                    cols[name] = pa.array(vals, self.schema.field(name).type)
        self._writer.write(pa.table(cols, schema=self.schema))
        self.rows += len(self._t)
        self._t, self._w, self._b = [], [], []

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
