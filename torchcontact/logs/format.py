"""The torchcontact log format: Parquet, one row per frame (the public contract of issue 4).

Input columns (see the README section "Processing logs"):

- ``t_ns``: int64 time stamp, ns.
- ``q``, ``qd``, ``qdd``: fixed-size (or plain) lists of float64 joint positions (rad or m),
  velocities and accelerations, ordered as the JSON list in the schema metadata key
  ``torchcontact.joint_names``. ``qd``/``qdd`` may be missing (derived from ``q``).
- ``ft.<sensor>``: 6 float64 ``[force (N); moment (N m)]`` in the sensor's declared frame and
  measure direction.
- ``tau_measured`` (optional): nv float64, NaN where a joint has no torque sensor.
- ``base.omega``, ``base.domega``, ``base.acc`` (optional): 3 float64 each, IMU on the base, base
  frame (rad/s, rad/s^2, proper acceleration m/s^2).
- ``contacts``: list of structs ``{link: string, kind: wrench|force|force_dir|known, position: 3
  float64 (m, link frame), direction: 3 float64 or null, wrench: 6 float64 or null}``; extra
  struct fields (e.g. ``true_force``) are carried to the output unchanged.

Output adds ``force`` and ``moment`` (3 float64, link frame, N and N m) to every contact and has
``joint_torques``, ``rank.<sensor>``, ``unknowns.<sensor>``, ``residual.<sensor>`` and ``status``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = [
    "BASE_COLUMNS",
    "META_DERIVED",
    "META_JOINT_NAMES",
    "META_RESIDUAL",
    "META_SENSORS",
    "META_URDF_SHA256",
    "META_VERSION",
    "contact_struct_type",
    "ft_column",
    "fixed_list",
    "input_schema",
    "joint_names_of",
    "vectors",
]

META_JOINT_NAMES = b"torchcontact.joint_names"
META_URDF_SHA256 = b"torchcontact.urdf_sha256"
META_VERSION = b"torchcontact.version"
META_SENSORS = b"torchcontact.sensors"
META_DERIVED = b"torchcontact.derived"
#: Output logs estimated with a learned F/T correction: JSON ``{"checkpoint", "weights_sha256",
#: "sensor", "kind"}`` (``torchcontact estimate --residual``).
META_RESIDUAL = b"torchcontact.residual"
#: Optional IMU columns and the :class:`torchcontact.BaseMotion` field each one fills.
BASE_COLUMNS = {"base.omega": "omega", "base.domega": "domega", "base.acc": "proper_acc"}


def ft_column(sensor: str) -> str:
    """Column name of a sensor's readings, ``ft.<sensor>``."""
    return f"ft.{sensor}"


def fixed_list(values: np.ndarray) -> Any:
    """A pyarrow ``fixed_size_list<double>[n]`` array from an ``(N, n)`` float array."""
    import pyarrow as pa

    values = np.ascontiguousarray(values, dtype=np.float64)
    n = values.shape[-1]
    return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1), pa.float64()), n)


def contact_struct_type(extra: Sequence[tuple[str, Any]] = ()) -> Any:
    """The struct type of one contact: link, kind, position, direction, wrench, then ``extra``."""
    import pyarrow as pa

    return pa.struct(
        [
            ("link", pa.string()),
            ("kind", pa.string()),
            ("position", pa.list_(pa.float64(), 3)),
            ("direction", pa.list_(pa.float64(), 3)),
            ("wrench", pa.list_(pa.float64(), 6)),
            *extra,
        ]
    )


def input_schema(
    joint_names: Sequence[str],
    sensors: Sequence[str],
    *,
    derivatives: bool = True,
    contact_extra: Sequence[tuple[str, Any]] = (),
    extra: Sequence[tuple[str, Any]] = (),
) -> Any:
    """The Parquet schema of an input log with the joint names in its metadata.

    Args:
        joint_names: nv joint names, the order of ``q``/``qd``/``qdd``.
        sensors: F/T sensor names (one ``ft.<sensor>`` column each).
        derivatives: include ``qd`` and ``qdd``.
        contact_extra: extra ``(name, type)`` fields of the contact struct.
        extra: extra ``(name, type)`` columns.

    Example:
        >>> input_schema(["a", "b"], ["base_ft"]).names
        ['t_ns', 'q', 'qd', 'qdd', 'ft.base_ft', 'contacts']
    """
    import pyarrow as pa

    nv = len(joint_names)
    fields = [("t_ns", pa.int64()), ("q", pa.list_(pa.float64(), nv))]
    if derivatives:
        fields += [("qd", pa.list_(pa.float64(), nv)), ("qdd", pa.list_(pa.float64(), nv))]
    fields += [(ft_column(s), pa.list_(pa.float64(), 6)) for s in sensors]
    fields += [("contacts", pa.list_(contact_struct_type(contact_extra))), *extra]
    return pa.schema(fields, metadata={META_JOINT_NAMES: json.dumps(list(joint_names))})


def joint_names_of(schema: Any, path: object = "") -> list[str]:
    """Joint names from the schema metadata key ``torchcontact.joint_names``.

    Raises:
        ValueError: the key is missing or not a JSON list of strings.
    """
    raw = (schema.metadata or {}).get(META_JOINT_NAMES)
    if raw is None:
        raise ValueError(
            f"{path}: no joint names; the log format needs the schema metadata key"
            f" {META_JOINT_NAMES.decode()} (a JSON list, the order of q/qd/qdd)"
        )
    names = json.loads(raw)
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{path}: {META_JOINT_NAMES.decode()} is not a JSON list of strings")
    return names


def vectors(column: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of a list column as an ``(N, n)`` float64 array.

    Args:
        column: a pyarrow (chunked) array of fixed-size or plain lists of numbers.
        n: expected length of every row.

    Returns:
        ``values`` ``(N, n)`` (NaN where a row is bad) and ``bad`` ``(N,)`` bool: the row is null
        or does not have ``n`` entries.

    Example:
        >>> import pyarrow as pa
        >>> v, bad = vectors(pa.array([[1.0, 2.0], [3.0], None]), 2)
        >>> v[0].tolist(), bad.tolist()
        ([1.0, 2.0], [False, True, True])
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    N = len(column)
    out = np.full((N, n), np.nan)
    if N == 0:
        return out, np.zeros(0, bool)
    null = np.asarray(column.is_null().to_numpy(zero_copy_only=False), bool)
    if pa.types.is_fixed_size_list(column.type) and column.type.list_size == n and not null.any():
        flat = column.flatten()  # honours the array's offset
        return np.asarray(flat.to_numpy(zero_copy_only=False), np.float64).reshape(N, n), null
    lengths = pc.list_value_length(column).fill_null(-1).to_numpy(zero_copy_only=False)
    bad = null | (lengths != n)
    flat = np.asarray(column.flatten().fill_null(np.nan).to_numpy(zero_copy_only=False), float)
    parent = pc.list_parent_indices(column).to_numpy(zero_copy_only=False)
    good_rows = ~bad
    keep = good_rows[parent]
    if keep.any():
        out[good_rows] = flat[keep].reshape(-1, n)
    return out, bad
