"""The torchcontact log format: Parquet, one row per frame; the one reader and writer of logs.

Every Parquet file torchcontact reads or writes goes through this module: the input logs of
``estimate``, the estimates, ``convert`` and ``simulate`` outputs, the F/T logs of the drivers, and
the training data. Files are written with page checksums, through a temporary name and an atomic
rename (a file with the final name is always complete); page checksums are verified when read.

Input columns (the public contract: docs/format.md):

- ``t_ns``: int64 time stamp, ns.
- ``q``, ``qd``, ``qdd``: fixed-size (or plain) lists of float64 joint positions (rad or m),
  velocities and accelerations, ordered as the JSON list in the schema metadata key
  ``torchcontact.joint_names``. ``qd``/``qdd`` may be missing (derived from ``q``).
- ``ft.<sensor>``: 6 float64 ``[force (N); moment (N m)]`` in the sensor's declared frame and
  measure direction.
- ``ft_cov.<sensor>`` (optional): 36 float64, the ``6 x 6`` covariance of that frame's
  ``ft.<sensor>`` noise, row-major, ``[N; N m]`` squared units, symmetric positive definite:
  ``estimate`` weighs each frame's solve by it (:func:`ft_cov_column`; ``docs/accuracy.md``).
- ``tau_measured`` (optional): nv float64, NaN where a joint has no torque sensor.
- ``base.omega``, ``base.domega``, ``base.acc`` (optional): 3 float64 each, IMU on the base, base
  frame (rad/s, rad/s^2, proper acceleration m/s^2).
- ``contacts``: list of structs ``{link: string, kind: wrench|force|force_dir|known, position: 3
  float64 (m, link frame), direction: 3 float64 or null, wrench: 6 float64 or null}``, and
  optionally (:data:`CONE_FIELDS`, for ``estimate --constraints``) ``normal: 3 float64 or null``
  (outward surface normal, link frame), ``friction: float64 or null``, ``cone_angle: float64 or
  null`` (rad) and ``pushing: bool or null``; extra struct fields (e.g. ``true_force``) are
  carried to the output unchanged. In memory these are
  :class:`~torchcontact.contacts.ContactRecords` (:func:`read_contacts`, :func:`contacts_column`).

Output (:func:`output_schema`) adds ``force`` and ``moment`` (3 float64, link frame, N and N m) to
every contact and has ``joint_torques``, ``rank.<sensor>``, ``unknowns.<sensor>``,
``nullity.<sensor>`` (``unknowns - rank``: the dimension of the force combinations the sensor
cannot see), ``residual.<sensor>``, ``status_code`` (the bits of :data:`torchcontact.STATUS`),
``status`` (its text, :func:`torchcontact.status_messages`) and ``status_detail`` (what the log
pipeline found, or null). A friction-cone constrained estimate also has ``converged.<sensor>``
(bool) and ``iterations.<sensor>`` (int64) of the interior-point solver and, on every contact,
``cone_active`` (bool: the cone binds) and ``outside_cone`` (bool: the unconstrained estimate of
the contact lies outside its cone; null unless the frame is well posed, ``rank == unknowns``).
A localizing estimate (``--localize``) adds the columns of
:func:`localization_fields` per localizing sensor (:data:`LOCALIZATION_COLUMNS`).
"""

from __future__ import annotations

import glob
import json
import os
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.contacts import ContactRecords
from torchcontact.errors import InputError, LogError

__all__ = [
    "BASE_COLUMNS",
    "BIAS_COLUMNS",
    "CONE_FIELDS",
    "LOCALIZATION_COLUMNS",
    "NUMBERS",
    "META_BIAS",
    "META_DERIVED",
    "META_FT_NOISE",
    "META_FT_PROFILES",
    "META_JOINT_NAMES",
    "META_LOCALIZE",
    "META_RESIDUAL",
    "META_SENSORS",
    "META_SOURCE",
    "META_ROBOT",
    "META_URDF_SHA256",
    "META_VERSION",
    "EncodedPart",
    "LogWriter",
    "PartIndex",
    "PartsWriter",
    "bias_column",
    "check_number_type",
    "check_outputs",
    "check_schema",
    "check_vector_type",
    "contact_struct_type",
    "arrow_scalar",
    "arrow_to_numpy",
    "contacts_column",
    "fixed_list",
    "ft_column",
    "ft_cov_column",
    "ft_log_schema",
    "input_schema",
    "iter_chunks",
    "joint_names_of",
    "joint_permutation",
    "localization_fields",
    "logged_robot",
    "numpy_to_arrow",
    "one_array",
    "encode_part",
    "open_log",
    "output_paths",
    "output_schema",
    "string_array",
    "read_contacts",
    "read_journal",
    "read_log_columns",
    "read_part",
    "read_part_index",
    "read_rows",
    "robot_metadata",
    "struct_list",
    "timestamps",
    "vectors",
    "write_journal",
    "write_part_index",
    "write_table",
]

META_JOINT_NAMES = b"torchcontact.joint_names"
META_URDF_SHA256 = b"torchcontact.urdf_sha256"
#: The robot a log was written for: JSON ``{"robot": NAME_OR_URDF_PATH, "ft_sensors": [SPEC]}``
#: (the ``--robot`` and ``--ft-sensor`` values, a path made absolute), beside
#: :data:`META_URDF_SHA256`; ``torchcontact estimate`` without ``--robot`` uses them.
META_ROBOT = b"torchcontact.robot"
META_VERSION = b"torchcontact.version"
META_SENSORS = b"torchcontact.sensors"
META_DERIVED = b"torchcontact.derived"
#: Where a converted log came from (``bag:<name>``, ``csv:<name>``).
META_SOURCE = b"torchcontact.source"
#: Output logs estimated with a learned F/T correction: JSON ``{"checkpoint", "weights_sha256",
#: "sensor", "kind"}`` (``torchcontact estimate --residual``).
META_RESIDUAL = b"torchcontact.residual"
#: Output logs estimated with ``--track-bias``: JSON ``{"method", "time_constant", "ft_std",
#: "sensors"}`` (the F/T offsets tracked over the whole log, columns :data:`ESTIMATE_BIAS_COLUMNS`).
META_BIAS = b"torchcontact.bias"
#: The F/T sensor profiles of a log (:mod:`torchcontact.drivers.profiles`): JSON ``{sensor:
#: profile name or TOML path}``; ``estimate`` takes a sensor's noise from its profile's datasheet
#: ``[noise]`` when neither ``--ft-noise`` nor an ``ft_cov.<sensor>`` column gives it.
META_FT_PROFILES = b"torchcontact.ft_profiles"
#: Output logs: the F/T noise each sensor's solve was weighted by, JSON ``{"weighted": bool,
#: "sensors": {sensor: {"source": text, "std": 6 floats or null}}}`` (``estimate``'s summary
#: ``noise``).
META_FT_NOISE = b"torchcontact.ft_noise"
#: Output logs with localized contacts (``torchcontact estimate --localize``): JSON of the
#: options (``links``, ``force_threshold``, ``accept_ambiguous``, ``ft_std``, ``ray``) and the
#: ``candidates`` links.
META_LOCALIZE = b"torchcontact.localize"
#: Optional IMU columns and the :class:`torchcontact.BaseMotion` field each one fills.
BASE_COLUMNS = {"base.omega": "omega", "base.domega": "domega", "base.acc": "proper_acc"}
#: Columns holding one value per joint, in the order of ``torchcontact.joint_names``.
JOINT_COLUMNS = ("q", "qd", "qdd", "tau_measured")
#: Options of every Parquet file written: page checksums (verified when read); no dictionary
#: encoding and statistics of ``t_ns`` only (random floats gain nothing from either, and they
#: halve the writing time).
WRITE_OPTIONS: dict[str, Any] = {
    "write_page_checksum": True,
    "compression": "snappy",
    "use_dictionary": False,
}


def ft_column(sensor: str) -> str:
    """Column name of a sensor's readings, ``ft.<sensor>``."""
    return f"ft.{sensor}"


#: The F/T bias columns, per sensor ``<prefix>.<sensor>``: prefix -> (field of the bias record
#: :meth:`torchcontact.online.bias.BiasState.as_dict`, pyarrow type name, width). ``bias``: the
#: offset subtracted from the reading [N; N m]; ``bias_std``: its standard deviation;
#: ``bias_since_update``: s since the last update (null before the first); ``bias_updated``:
#: this frame updated it. ``torchcontact run --track-bias --out`` writes all four;
#: ``estimate --track-bias`` (the smoothed offset of the whole log) the first two.
BIAS_COLUMNS = {
    "bias": ("offset", "list", 6),
    "bias_std": ("std", "list", 6),
    "bias_since_update": ("since_update", "float64", 1),
    "bias_updated": ("updated", "bool", 1),
}
#: The bias columns of an estimated log (``estimate --track-bias``).
ESTIMATE_BIAS_COLUMNS = ("bias", "bias_std")


def bias_column(prefix: str, sensor: str) -> str:
    """The column of a bias quantity of a sensor, e.g. ``bias.base_ft`` (:data:`BIAS_COLUMNS`)."""
    return f"{prefix}.{sensor}"


def ft_cov_column(sensor: str) -> str:
    """The per-frame F/T noise covariance column of a sensor (36 float64, row-major ``6 x 6``).

    Example:
        >>> ft_cov_column("base_ft")
        'ft_cov.base_ft'
    """
    return f"ft_cov.{sensor}"


# ------------------------------------------------------------- numpy <-> Arrow, without pandas
# pyarrow imports pandas (0.3-0.6 s) the first time it converts from or to numpy or Python
# values: pa.array(ndarray or list), Array.to_numpy(), np.asarray(array), pa.scalar(...), and
# compute functions given numpy or Python arguments. Arrays built from buffers, their buffers read
# as numpy, and compute functions on Arrow arguments do not. Every conversion on the log job's path
# goes through these helpers, so that ``torchcontact estimate`` never imports pandas.


def _numpy_dtype(typ: Any) -> np.dtype:
    """The numpy dtype of a fixed-width Arrow type's values (temporal types: their integers)."""
    import pyarrow as pa

    t = pa.types
    if not (t.is_floating(typ) or t.is_integer(typ) or t.is_temporal(typ)):
        raise TypeError(f"no numpy dtype for Arrow {typ}")
    size = typ.bit_width // 8
    if t.is_floating(typ):
        return np.dtype(f"f{size}")
    if t.is_unsigned_integer(typ):
        return np.dtype(f"u{size}")
    return np.dtype(f"i{size}")


def one_array(column: Any) -> Any:
    """A pyarrow array, or a chunked array as one array: a single chunk as it is, no copy.

    ``ChunkedArray.combine_chunks`` copies even a single chunk (2 MB per 8192 frames of ``q``).
    """
    import pyarrow as pa

    if not isinstance(column, pa.ChunkedArray):
        return column
    return column.chunk(0) if column.num_chunks == 1 else column.combine_chunks()


def arrow_to_numpy(values: Any, dtype: Any = None, fill: Any = None) -> np.ndarray:
    """A pyarrow array of numbers, booleans or time stamps as a 1-D numpy array.

    Without pandas (which ``Array.to_numpy`` imports). A single chunk without nulls whose type
    matches ``dtype`` is returned without a copy, as a read-only view of the Arrow buffer (as
    ``to_numpy`` does); sliced arrays (``offset != 0``) are honoured. Booleans are unpacked from
    their bitmap. Temporal types give their integers (e.g. ns of a ``timestamp("ns")``).

    Args:
        values: a pyarrow ``Array`` or ``ChunkedArray`` of length N.
        dtype: the numpy dtype of the result (default: that of the Arrow type).
        fill: the value of null entries. Default: NaN, and the result is float64 unless
            ``dtype`` is a float type (as ``to_numpy(zero_copy_only=False)`` does for numbers).

    Returns:
        ``(N,)`` numpy array.

    Raises:
        TypeError: a type that is not fixed-width (strings, lists), or nulls with no ``fill``
            in an integer or boolean ``dtype``.

    Example:
        >>> a = numpy_to_arrow(np.array([1, 2, 3]), mask=np.array([False, True, False]))
        >>> arrow_to_numpy(a).tolist(), arrow_to_numpy(a.slice(2), np.int32).tolist()
        ([1.0, nan, 3.0], [3])
        >>> arrow_to_numpy(a, fill=-1).tolist()
        [1, -1, 3]
    """
    import pyarrow as pa

    if isinstance(values, pa.ChunkedArray) and values.num_chunks > 1:
        return np.concatenate([arrow_to_numpy(c, dtype, fill) for c in values.chunks])
    values = one_array(values)  # no chunk: an empty array
    typ = values.type
    n, off = len(values), values.offset
    if pa.types.is_boolean(typ):
        buf = values.buffers()[1]
        bits = np.frombuffer(buf, np.uint8) if buf is not None and n else np.zeros(0, np.uint8)
        out = np.unpackbits(bits, count=off + n, bitorder="little")[off:].view(bool)
    elif pa.types.is_null(typ):
        out = np.zeros(n, np.float64)
    else:
        natural = _numpy_dtype(typ)
        buf = values.buffers()[1]
        if buf is None or n == 0:
            out = np.zeros(n, natural)
        else:
            out = np.frombuffer(buf, natural, count=n, offset=off * natural.itemsize)
            out.flags.writeable = False  # Arrow's memory, maybe shared: read-only, as to_numpy
    if values.null_count:
        target = np.dtype(dtype) if dtype is not None else out.dtype
        if fill is None:
            if target.kind != "f":
                if dtype is not None:
                    raise TypeError(f"{values.null_count} nulls and no fill for {target}")
                target = np.dtype(np.float64)
            fill = np.nan
        out = out.astype(target)  # a copy
        out[arrow_to_numpy(values.is_null())] = fill
        return out
    return out if dtype is None else out.astype(dtype, copy=False)


def _validity(mask: np.ndarray | None) -> tuple[Any, int]:
    """An Arrow validity bitmap (LSB first) for ``mask`` (True: null), and the null count."""
    import pyarrow as pa

    if mask is None:
        return None, 0
    mask = np.asarray(mask, bool).reshape(-1)
    nulls = int(mask.sum())
    if not nulls:
        return None, 0
    return pa.py_buffer(np.packbits(~mask, bitorder="little")), nulls


def numpy_to_arrow(values: np.ndarray, type: Any = None, mask: np.ndarray | None = None) -> Any:
    """A pyarrow array from a 1-D numpy array of numbers or booleans (no pandas).

    As ``pa.array(values, type, mask=mask)``: NaN stays a value, only ``mask`` makes nulls. The
    Arrow array shares the memory of a contiguous ``values`` of its dtype (no copy).

    Args:
        values: ``(N,)`` array (any shape is flattened in C order).
        type: the Arrow type (a fixed-width number, time stamp or ``bool``; default: from the
            dtype). Values are converted to its numpy dtype.
        mask: ``(N,)`` bool, True where the entry is null.

    Returns:
        A pyarrow ``Array`` of length N.

    Example:
        >>> numpy_to_arrow(np.array([1.0, np.nan]), mask=np.array([True, False])).to_pylist()
        [None, nan]
    """
    import pyarrow as pa

    values = np.asarray(values)
    if type is None:
        type = pa.from_numpy_dtype(values.dtype)
    validity, nulls = _validity(mask)
    if pa.types.is_boolean(type):
        flat = np.asarray(values, bool).reshape(-1)
        data = pa.py_buffer(np.packbits(flat, bitorder="little"))
    else:
        flat = np.ascontiguousarray(values, _numpy_dtype(type)).reshape(-1)
        data = pa.py_buffer(flat)
    return pa.Array.from_buffers(type, len(flat), [validity, data], null_count=nulls)


def string_array(texts: Sequence[str | None], type: Any = None) -> Any:
    """A pyarrow ``string`` array from Python strings, None as null (no pandas).

    Args:
        texts: N strings or None.
        type: ``pa.string()`` (default) or another string type to cast to.

    Example:
        >>> string_array(["force", None, "é"]).to_pylist()
        ['force', None, 'é']
    """
    import pyarrow as pa

    encoded = [b"" if t is None else t.encode("utf-8") for t in texts]
    lengths = np.fromiter(map(len, encoded), np.int64, len(encoded))
    offsets = np.zeros(len(encoded) + 1, np.int64)
    np.cumsum(lengths, out=offsets[1:])
    large = offsets[-1] >= 2**31
    mask = np.fromiter((t is None for t in texts), bool, len(encoded))
    validity, nulls = _validity(mask)
    arr = pa.Array.from_buffers(
        pa.large_string() if large else pa.string(),
        len(encoded),
        [validity, pa.py_buffer(offsets if large else offsets.astype(np.int32)),
         pa.py_buffer(b"".join(encoded))],
        null_count=nulls,
    )  # fmt: skip
    return arr if type is None or arr.type == type else arr.cast(type)


def arrow_scalar(value: Any, type: Any) -> Any:
    """A pyarrow scalar of ``type`` without pandas (which ``pa.scalar`` imports).

    Args:
        value: None (null), a number, bool or string, or ``[]`` (an empty list).
        type: its Arrow type.

    Example:
        >>> import pyarrow as pa
        >>> arrow_scalar(None, pa.int64()).is_valid, arrow_scalar(2, pa.int8()).as_py()
        (False, 2)
    """
    import pyarrow as pa

    if value is None:
        return pa.nulls(1, type)[0]
    if isinstance(value, str):
        return string_array([value], type)[0]
    if isinstance(value, list) and not value and pa.types.is_list(type):
        empty = pa.nulls(0, type.value_type)
        return pa.ListArray.from_arrays(numpy_to_arrow(np.zeros(2, np.int32)), empty, type=type)[0]
    return numpy_to_arrow(np.array([value]), type)[0]


def fixed_list(values: np.ndarray) -> Any:
    """A pyarrow ``fixed_size_list<double>[n]`` array from an ``(N, n)`` float array."""
    import pyarrow as pa

    values = np.ascontiguousarray(values, dtype=np.float64)
    n = values.shape[-1]
    return pa.FixedSizeListArray.from_arrays(numpy_to_arrow(values, pa.float64()), n)


#: Optional contact fields of the friction-cone constrained estimate: log field -> the
#: :class:`~torchcontact.contacts.ContactRecords` attribute it fills.
CONE_FIELDS = {"normal": "normals", "friction": "friction", "cone_angle": "cone_angle",
               "pushing": "pushing"}  # fmt: skip


def _cone_types() -> list[tuple[str, Any]]:
    import pyarrow as pa

    return [("normal", pa.list_(pa.float64())), ("friction", pa.float64()),
            ("cone_angle", pa.float64()), ("pushing", pa.bool_())]  # fmt: skip


def contact_struct_type(extra: Sequence[tuple[str, Any]] = (), cone: bool = False) -> Any:
    """The struct type of one contact: link, kind, position, direction, wrench, then ``extra``.

    Args:
        extra: further ``(name, type)`` fields.
        cone: also the friction-cone fields (:data:`CONE_FIELDS`) after ``wrench``.

    Example:
        >>> contact_struct_type(cone=True).names[5:]
        ['normal', 'friction', 'cone_angle', 'pushing']
    """
    import pyarrow as pa

    return pa.struct(
        [
            ("link", pa.string()),
            ("kind", pa.string()),
            ("position", pa.list_(pa.float64(), 3)),
            # fields that may be null (not given) are variable-length lists: pyarrow < 26
            # cannot read a null entry of a fixed-size list back from Parquet (apache/arrow#35692)
            ("direction", pa.list_(pa.float64())),
            ("wrench", pa.list_(pa.float64())),
            *(_cone_types() if cone else []),
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
    metadata: Mapping[bytes, bytes | str] | None = None,
    cone: bool = False,
) -> Any:
    """The Parquet schema of an input log with the joint names in its metadata.

    Args:
        joint_names: nv joint names, the order of ``q``/``qd``/``qdd``.
        sensors: F/T sensor names (one ``ft.<sensor>`` column each).
        derivatives: include ``qd`` and ``qdd``.
        contact_extra: extra ``(name, type)`` fields of the contact struct.
        extra: extra ``(name, type)`` columns.
        metadata: further schema metadata.
        cone: contacts with the friction-cone fields (:data:`CONE_FIELDS`).

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
    fields += [("contacts", pa.list_(contact_struct_type(contact_extra, cone))), *extra]
    meta = {META_JOINT_NAMES: json.dumps(list(joint_names)), **(metadata or {})}
    return pa.schema(fields, metadata=meta)


def ft_log_schema(sensor: str) -> Any:
    """Schema of an F/T-only log (the drivers' ``--out``): ``t_ns`` and ``ft.<sensor>``.

    Example:
        >>> ft_log_schema("ft300").names
        ['t_ns', 'ft.ft300']
    """
    import pyarrow as pa

    return pa.schema([("t_ns", pa.int64()), (ft_column(sensor), pa.list_(pa.float64(), 6))])


def output_schema(
    joint_names: Sequence[str],
    sensors: Sequence[str],
    contact_fields: Sequence[tuple[str, Any]],
    metadata: Mapping[bytes, bytes | str],
    constraints: bool = False,
    localize: Sequence[str] = (),
    bias: bool = False,
) -> Any:
    """Schema of an estimated log.

    Args:
        joint_names: nv joint names, the order of ``joint_torques``.
        sensors: the F/T sensors used.
        contact_fields: ``(name, type)`` fields of the input contact struct (empty: no
            ``contacts`` column in the input); ``force`` and ``moment`` are appended.
        metadata: schema metadata (joint names are added).
        constraints: a friction-cone constrained estimate: contacts get ``cone_active`` and
            ``outside_cone``, each
            sensor ``converged.<s>`` and ``iterations.<s>``.
        localize: the sensors whose contact is localized (``estimate --localize``): their
            :func:`localization_fields` come after ``status_detail``.
        bias: the F/T offsets were tracked (``estimate --track-bias``): per sensor
            ``bias.<s>`` and ``bias_std.<s>`` (6 float64, :data:`ESTIMATE_BIAS_COLUMNS`).

    Returns:
        ``t_ns, contacts, joint_torques, rank.<s>, unknowns.<s>, nullity.<s>, residual.<s>
        [, converged.<s>, iterations.<s>] [, bias.<s>, bias_std.<s>], status_code, status,
        status_detail [, localize_*.<s>]``.
    """
    import pyarrow as pa

    nv = len(joint_names)
    contact = pa.struct(
        [
            *[pa.field(n, t) for n, t in contact_fields],
            pa.field("force", pa.list_(pa.float64(), 3)),
            pa.field("moment", pa.list_(pa.float64(), 3)),
            *(
                [pa.field("cone_active", pa.bool_()), pa.field("outside_cone", pa.bool_())]
                if constraints
                else []
            ),
        ]
    )
    fields = [("t_ns", pa.int64()), ("contacts", pa.list_(contact))]
    fields.append(("joint_torques", pa.list_(pa.float64(), nv)))
    for s in sensors:
        fields += [(f"rank.{s}", pa.int64()), (f"unknowns.{s}", pa.int64())]
        fields += [(f"nullity.{s}", pa.int64()), (f"residual.{s}", pa.float64())]
        if constraints:
            fields += [(f"converged.{s}", pa.bool_()), (f"iterations.{s}", pa.int64())]
        if bias:
            fields += [
                (bias_column(p, s), pa.list_(pa.float64(), 6)) for p in ESTIMATE_BIAS_COLUMNS
            ]
    fields += [("status_code", pa.int64()), ("status", pa.string())]
    fields.append(("status_detail", pa.string()))
    fields += localization_fields(localize)
    meta = {**metadata, META_JOINT_NAMES: json.dumps(list(joint_names))}
    return pa.schema(fields, metadata=meta)


#: Per-frame localization columns of ``estimate --localize`` (one set per localizing sensor
#: ``<s>``): field -> (pyarrow type name, meaning). See :mod:`torchcontact.localize`.
LOCALIZATION_COLUMNS = {
    "localize_link": ("string", "link of the localized contact (null: none)"),
    "localize_position": ("3 float64", "contact point, link frame, m"),
    "localize_normal": ("3 float64", "outward surface normal at the point, link frame"),
    "localize_force": ("3 float64", "pure-force estimate b[:3], link frame, N"),
    "localize_moment_residual": ("float64", "|f . m| / |f|, N m"),
    "localize_position_std": ("float64", "sqrt(trace(cov)) of the point from the F/T noise, m"),
    "localize_candidates": ("int64", "distinct points where the line enters the links"),
    "localize_status_code": ("int64", "bits of torchcontact.LOCALIZE_STATUS (0: localized)"),
    "localize_status": ("string", "the code's text"),
}


def localization_fields(sensors: Sequence[str]) -> list[tuple[str, Any]]:
    """The ``(name, type)`` columns of a localization (``estimate --localize``), per sensor.

    Args:
        sensors: the sensors that localize a contact.

    Returns:
        For each sensor ``s``, the :data:`LOCALIZATION_COLUMNS` as ``<field>.<s>``.

    Example:
        >>> [n for n, _ in localization_fields(["wrist"])][:2]
        ['localize_link.wrist', 'localize_position.wrist']
    """
    import pyarrow as pa

    types = {"string": pa.string(), "3 float64": pa.list_(pa.float64(), 3),
             "float64": pa.float64(), "int64": pa.int64()}  # fmt: skip
    return [(f"{name}.{s}", types[typ]) for s in sensors
            for name, (typ, _) in LOCALIZATION_COLUMNS.items()]  # fmt: skip


def joint_permutation(
    names: Sequence[str],
    model_names: Sequence[str],
    robot: str,
    source: object = "",
    *,
    strict: bool = False,
) -> np.ndarray:
    """Index of each of the robot's joints in a log's joint list (joints matched by name).

    The log must name every one of the robot's joint coordinates, in any order. Joints the robot
    lacks (a gripper's, a second arm's) are left out with one warning naming them, or refused
    with ``strict`` (``--strict-joints``). This is the one place where ``estimate``, ``plot``
    and training match a log's joints to a robot.

    Args:
        names: the log's joint names (:func:`joint_names_of`).
        model_names: the robot's coordinates (``model.joint_names``).
        robot: the robot's name, for messages.
        source: the log, for messages.
        strict: refuse joints the robot lacks instead of leaving them out.

    Returns:
        ``(nv,)`` int64 ``perm`` with ``log_vector[..., perm]`` in the robot's order.

    Raises:
        LogError: robot joints the log lacks, extra joints with ``strict`` (naming them), or
            duplicate names.

    Warns:
        UserWarning: the log's joints the robot lacks, which are left out (not ``strict``).

    Example:
        >>> joint_permutation(["b", "a"], ["a", "b"], "robot").tolist()
        [1, 0]
    """
    names, model_names = list(names), list(model_names)
    missing = [n for n in model_names if n not in names]
    extra = [n for n in names if n not in model_names]
    if missing or (extra and strict):
        msg = f"{source}: joint names of the log do not match {robot} (matched by name):"
        if missing:
            msg += f" the log lacks joints {missing}"
        if extra:
            msg += f" extra {extra} (mimic and fixed joints are not"
            msg += " coordinates)"
        raise LogError(msg)
    if len(set(names)) != len(names):
        raise LogError(f"{source}: duplicate joint names {names}")
    if extra:
        warnings.warn(
            f"{source}: leaving out joints {extra}, which {robot} does not have"
            " (--strict-joints refuses them)",
            UserWarning,
            stacklevel=2,
        )
    return np.array([names.index(n) for n in model_names], dtype=np.int64)


def joint_names_of(schema: Any, path: object = "") -> list[str]:
    """Joint names from the schema metadata key ``torchcontact.joint_names``.

    Raises:
        LogError: the key is missing or not a JSON list of strings.
    """
    raw = (schema.metadata or {}).get(META_JOINT_NAMES)
    if raw is None:
        raise LogError(
            f"{path}: no joint names; the log format needs the schema metadata key"
            f" {META_JOINT_NAMES.decode()} (a JSON list, the order of q/qd/qdd)"
        )
    try:
        names = json.loads(raw)
    except ValueError:
        names = None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise LogError(f"{path}: {META_JOINT_NAMES.decode()} is not a JSON list of strings")
    return names


def robot_metadata(robot: str, urdf_sha256: str, ft_sensors: Sequence[str] = ()) -> dict:
    """Schema metadata naming a log's robot (:data:`META_ROBOT`, :data:`META_URDF_SHA256`).

    Args:
        robot: a robot name (``tcarm``) or an absolute URDF path.
        urdf_sha256: sha256 of the URDF text (``RobotModel.urdf_sha256``).
        ft_sensors: declared sensors (``--ft-sensor`` specs), if any.

    Example:
        >>> robot_metadata("tcarm", "ab12")[META_ROBOT]
        '{"robot": "tcarm", "ft_sensors": []}'
    """
    return {
        META_ROBOT: json.dumps({"robot": str(robot), "ft_sensors": [str(s) for s in ft_sensors]}),
        META_URDF_SHA256: urdf_sha256,
    }


def logged_robot(schema: Any) -> tuple[dict | None, str]:
    """The robot recorded in a log's metadata: ``(META_ROBOT as a dict or None, URDF sha256)``.

    A malformed :data:`META_ROBOT` counts as absent; the sha256 is ``""`` when not recorded.
    """
    meta = getattr(schema, "metadata", None) or {}
    sha = meta.get(META_URDF_SHA256, b"").decode()
    try:
        robot = json.loads(meta[META_ROBOT]) if META_ROBOT in meta else None
    except ValueError:
        robot = None
    ok = isinstance(robot, dict) and isinstance(robot.get("robot"), str)
    ok = ok and all(isinstance(s, str) for s in robot.get("ft_sensors", []))  # type: ignore[union-attr]
    return (robot if ok else None), sha


#: What a numeric log column may hold: numbers that convert to float64 without loss.
NUMBERS = "float64 (integers, float16/32 and decimals are converted)"


def _is_number(typ: Any) -> bool:
    """A type whose values convert to float64: integers, floats, decimals (or all-null)."""
    import pyarrow as pa

    t = pa.types
    return t.is_integer(typ) or t.is_floating(typ) or t.is_decimal(typ) or t.is_null(typ)


def _is_list(typ: Any) -> bool:
    import pyarrow as pa

    t = pa.types
    return t.is_list(typ) or t.is_large_list(typ) or t.is_fixed_size_list(typ)


def check_vector_type(typ: Any, name: str, source: object = "") -> None:
    """Refuse a column type that is not a list of numbers (or all-null).

    Args:
        typ: the pyarrow type of the column.
        name: the column, for the message (``q``, ``ft.<sensor>``, ``contacts.position``).
        source: the file, for the message.

    Raises:
        LogError: naming the column, its type and the expected type.

    Example:
        >>> import pyarrow as pa
        >>> check_vector_type(pa.list_(pa.int64()), "ft.s")  # int counts convert: accepted
        >>> check_vector_type(pa.list_(pa.string()), "q")
        Traceback (most recent call last):
        ...
        torchcontact.errors.LogError: column 'q' is list<item: string>; expected a list of \
float64 (integers, float16/32 and decimals are converted)
    """
    import pyarrow as pa

    if pa.types.is_null(typ) or (_is_list(typ) and _is_number(typ.value_type)):
        return
    where = f"{source}: " if str(source) else ""
    raise LogError(f"{where}column {name!r} is {typ}; expected a list of {NUMBERS}")


def check_number_type(typ: Any, name: str, source: object = "") -> None:
    """Refuse a scalar column type that does not convert to float64 (see :data:`NUMBERS`).

    Raises:
        LogError: naming the column, its type and the expected type.
    """
    if not _is_number(typ):
        where = f"{source}: " if str(source) else ""
        raise LogError(f"{where}column {name!r} is {typ}; expected {NUMBERS}")


#: Integers beyond this magnitude have no exact float64.
_EXACT_INT = 2**53


def _float64(values: Any) -> Any:
    """A numeric pyarrow array as float64, null where a value has no exact float64.

    Integers beyond 2**53 in magnitude would be rounded: they become null (NaN), a per-value
    problem like a NaN reading, never a silently different number.
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    if pa.types.is_float64(values.type):
        return values
    if pa.types.is_integer(values.type):
        big, small = arrow_scalar(_EXACT_INT, pa.int64()), arrow_scalar(-_EXACT_INT, pa.int64())
        lossy = pc.or_(pc.greater(values, big), pc.less(values, small))
        if pc.any(lossy).as_py():
            values = pc.if_else(lossy, arrow_scalar(None, values.type), values)
    return pc.cast(values, pa.float64(), safe=False)


def vectors(
    column: Any, n: int, name: str = "", source: object = ""
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of a list column as an ``(N, n)`` float64 array.

    Values of any type of :data:`NUMBERS` are converted (int counts, float32, decimals); nulls
    inside a row, and integers beyond 2**53 in magnitude (no exact float64), make it NaN there.

    Args:
        column: a pyarrow (chunked) array of fixed-size or plain lists of numbers, or an
            all-null column.
        n: expected length of every row.
        name: the column, for messages.
        source: the file, for messages.

    Returns:
        ``values`` ``(N, n)`` (NaN where a row is bad) and ``bad`` ``(N,)`` bool: the row is null
        or does not have ``n`` entries.

    Raises:
        LogError: a column that is not a list of numbers (naming the column, its type and the
            expected type).

    Example:
        >>> import pyarrow as pa
        >>> v, bad = vectors(pa.array([[1.0, 2.0], [3.0], None]), 2)
        >>> v[0].tolist(), bad.tolist()
        ([1.0, 2.0], [False, True, True])
        >>> vectors(pa.array([[1, None], [2**53 + 1, 0]]), 2)[0].tolist()  # int counts
        [[1.0, nan], [nan, 0.0]]
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    column = one_array(column)
    check_vector_type(column.type, name or "a vector column", source)
    N = len(column)
    if N == 0 or pa.types.is_null(column.type) or column.null_count == N:
        return np.full((N, n), np.nan), np.ones(N, bool)
    flat = _float64(column.flatten())  # flatten honours the array's offset
    if not column.null_count and len(flat) == N * n:
        # the common cases: every row has n values (a fixed size n, or offsets n apart); the
        # values as they are, no copy
        if (
            pa.types.is_fixed_size_list(column.type)
            or (np.diff(arrow_to_numpy(column.offsets)) == n).all()
        ):
            return arrow_to_numpy(flat, np.float64).reshape(N, n), np.zeros(N, bool)
    null = arrow_to_numpy(column.is_null())
    out = np.full((N, n), np.nan)
    lengths = arrow_to_numpy(pc.list_value_length(column), fill=-1)
    bad = null | (lengths != n)
    flat = arrow_to_numpy(flat, np.float64)
    parent = arrow_to_numpy(pc.list_parent_indices(column))
    good_rows = ~bad
    keep = good_rows[parent]
    if keep.any():
        out[good_rows] = flat[keep].reshape(-1, n)
    return out, bad


def _is_text(typ: Any) -> bool:
    import pyarrow as pa

    t = pa.types
    if t.is_dictionary(typ):
        typ = typ.value_type
    return t.is_string(typ) or t.is_large_string(typ) or t.is_null(typ)


def check_schema(schema: Any, source: object = "") -> None:
    """Refuse a log whose columns of the log format have types no reader can use.

    The columns of the format that are present are checked: ``t_ns`` integers or time stamps;
    ``q``, ``qd``, ``qdd``, ``tau_measured``, ``ft.<sensor>`` and ``base.*`` lists of numbers
    (:data:`NUMBERS`); ``contacts`` a list of structs whose ``link`` and ``kind`` are strings,
    ``position``, ``direction``, ``wrench`` and ``normal`` lists of numbers, ``friction`` and
    ``cone_angle`` numbers and ``pushing`` a bool. Other columns are not checked. Values (nulls,
    NaN, wrong lengths) are per-frame matters, not checked here.

    Raises:
        LogError: the first offending column: its name, its type and the expected type.
    """
    import pyarrow as pa

    where = f"{source}: " if str(source) else ""
    for field in schema:
        name, typ = field.name, field.type
        if name == "t_ns":
            if not (pa.types.is_integer(typ) or pa.types.is_timestamp(typ)):
                raise LogError(f"{where}column 't_ns' is {typ}; expected int64 time stamps (ns)")
        elif name in JOINT_COLUMNS or name.startswith("ft.") or name in BASE_COLUMNS:
            check_vector_type(typ, name, source)
        elif name == "contacts":
            ok = (pa.types.is_list(typ) or pa.types.is_large_list(typ)) and pa.types.is_struct(
                typ.value_type
            )
            if not ok:
                raise LogError(f"{where}column 'contacts' is {typ}; expected a list of structs")
            for sub in typ.value_type:
                label = f"contacts.{sub.name}"
                if sub.name in ("link", "kind") and not _is_text(sub.type):
                    raise LogError(f"{where}column {label!r} is {sub.type}; expected a string")
                if sub.name in ("position", "direction", "wrench", "normal"):
                    check_vector_type(sub.type, label, source)
                elif sub.name in ("friction", "cone_angle"):
                    check_number_type(sub.type, label, source)
                elif sub.name == "pushing" and not (
                    pa.types.is_boolean(sub.type) or _is_number(sub.type)
                ):
                    raise LogError(f"{where}column {label!r} is {sub.type}; expected a bool")


# ---------------------------------------------------------------------- contacts <-> Arrow
def read_contacts(
    column: Any, cones: bool = True
) -> tuple[ContactRecords, dict[str, Any], dict[str, np.ndarray]]:
    """The records of a ``contacts`` column (list of structs).

    Args:
        column: a pyarrow (chunked) ``list<struct>`` array; null rows are frames without contact.
        cones: read the friction-cone fields' values; with False their types are checked only
            (an estimate without constraints does not use them) and the records have none.

    Returns:
        ``(records, fields, malformed)``: :class:`~torchcontact.contacts.ContactRecords` (frames
        numbered from 0 within ``column``; NaN where a vector is missing or malformed), the
        struct's child arrays by field name (to carry extra fields), and for ``position``,
        ``direction`` and ``wrench`` (and ``normal`` when the struct has it) an ``(M,)`` bool
        mask of records whose field is null or of the wrong length (missing fields: all True).
        The friction-cone fields (:data:`CONE_FIELDS`) fill the records' ``normals``,
        ``friction``, ``cone_angle`` and ``pushing`` when the struct has them (null: NaN).

    Raises:
        LogError: a field of the wrong type (naming it, its type and the expected one): ``link``
            and ``kind`` strings, vectors lists of numbers, the friction-cone fields numbers
            (``pushing``: bool).
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    lst = one_array(column)
    if lst.null_count:  # null rows -> empty lists (if_else rebuilds the whole column)
        lst = pc.if_else(lst.is_null(), arrow_scalar([], lst.type), lst)
    structs = lst.flatten()
    frame = arrow_to_numpy(pc.list_parent_indices(lst), np.int64)
    fields = dict(zip([f.name for f in structs.type], structs.flatten(), strict=True))
    M = len(frame)
    vec: dict[str, np.ndarray] = {}
    malformed: dict[str, np.ndarray] = {}
    for key in ("link", "kind"):
        if key in fields and not _is_text(fields[key].type):
            raise LogError(f"column 'contacts.{key}' is {fields[key].type}; expected a string")
    for name, width in (("position", 3), ("direction", 3), ("wrench", 6)):
        if name in fields:
            vec[name], malformed[name] = vectors(fields[name], width, f"contacts.{name}")
        else:
            vec[name], malformed[name] = np.full((M, width), np.nan), np.ones(M, bool)
    cone: dict[str, np.ndarray] = {}
    if "normal" in fields:
        if cones:
            cone["normals"], malformed["normal"] = vectors(fields["normal"], 3, "contacts.normal")
        else:
            check_vector_type(fields["normal"].type, "contacts.normal")
    for name in ("friction", "cone_angle", "pushing"):
        if name in fields:
            col = fields[name]
            typ = pa.types
            if not cones and (typ.is_floating(col.type) or typ.is_integer(col.type)
                              or typ.is_boolean(col.type)):  # fmt: skip
                col = col.slice(0, 0)  # converts: nothing to check in the values
            try:
                col = pc.cast(col, pa.float64())
            except (pa.ArrowException, NotImplementedError):
                expected = "a bool" if name == "pushing" else NUMBERS
                raise LogError(
                    f"column 'contacts.{name}' is {fields[name].type}; expected {expected}"
                ) from None
            if cones:
                cone[name] = arrow_to_numpy(col, np.float64)

    def names(key: str) -> tuple[np.ndarray, np.ndarray]:
        """Distinct names (None last) and each record's index: Arrow's dictionary encoding."""
        if key not in fields:
            return np.array([None], dtype=object), np.zeros(M, np.int64)
        enc = pc.dictionary_encode(fields[key])
        uniq = np.array([*enc.dictionary.to_pylist(), None], dtype=object)
        return uniq, arrow_to_numpy(enc.indices, np.int64, fill=len(uniq) - 1)

    ln, lc = names("link")
    kn, kc = names("kind")
    records = ContactRecords(
        frame,
        ln[lc],
        kn[kc],
        vec["position"],
        vec["direction"] if "direction" in fields else None,
        vec["wrench"] if "wrench" in fields else None,
        (ln, lc, kn, kc),
        **cone,
    )
    return records, fields, malformed


def contacts_column(
    records: ContactRecords,
    frames: int,
    extra: Mapping[str, Any] | None = None,
    struct_type: Any = None,
) -> Any:
    """A ``contacts`` column (list of structs, one list per frame) from records.

    Args:
        records: M records of frames ``0 .. frames - 1``, ordered by frame.
        frames: number of rows.
        extra: further struct fields, each an ``(M,)`` pyarrow array or an ``(M, n)`` float array
            (written as a fixed-size list), in record order.
        struct_type: the struct type to cast to (default :func:`contact_struct_type` with the
            extra fields' types).

    Returns:
        A pyarrow ``list<struct>`` array of length ``frames``. Directions, wrenches and normals
        that are all NaN (not given), NaN friction coefficients, cone angles and pushing flags
        are written as null. The friction-cone fields are written when the records carry one of
        them (or ``struct_type`` has them).

    Raises:
        InputError: records not ordered by frame, or a frame outside ``[0, frames)``.
    """
    import pyarrow as pa

    f = records.frame
    if len(f) and (np.any(np.diff(f) < 0) or f[0] < 0 or f[-1] >= frames):
        raise InputError(f"contact records must be ordered by frame within [0, {frames})")

    def nullable(values: np.ndarray | None, width: int) -> Any:
        # a variable-length list (see contact_struct_type): null where all NaN (not given)
        if values is None:
            return pa.nulls(len(f), pa.list_(pa.float64()))
        missing = np.isnan(values).all(-1)
        flat = numpy_to_arrow(values[~missing], pa.float64())
        offsets = np.r_[0, np.cumsum(np.where(missing, 0, width))].astype(np.int32)
        mask = numpy_to_arrow(missing) if missing.any() else None
        return pa.ListArray.from_arrays(numpy_to_arrow(offsets), flat, mask=mask)

    def scalars(values: np.ndarray | None, typ: Any) -> Any:
        if values is None:
            return pa.nulls(len(f), typ)
        return numpy_to_arrow(values, pa.float64(), mask=np.isnan(values)).cast(typ)

    children: dict[str, Any] = {
        "link": string_array(list(records.links)),
        "kind": string_array(list(records.kinds)),
        "position": fixed_list(records.positions),
        "direction": nullable(records.directions, 3),
        "wrench": nullable(records.wrenches, 6),
        "normal": nullable(records.normals, 3),
    }
    for name, typ in _cone_types()[1:]:
        children[name] = scalars(getattr(records, CONE_FIELDS[name]), typ)
    for name, value in (extra or {}).items():
        children[name] = fixed_list(value) if isinstance(value, np.ndarray) else value
    if struct_type is None:
        extra_types = [(n, children[n].type) for n in (extra or {})]
        struct_type = contact_struct_type(extra_types, cone=bool(records.cone_fields))
    return struct_list(children, f, frames, struct_type)


def struct_list(
    children: Mapping[str, Any], frame: np.ndarray, frames: int, struct_type: Any
) -> Any:
    """A ``list<struct>`` column from per-record field arrays and each record's frame.

    Args:
        children: field name -> ``(M,)`` pyarrow array, for every field of ``struct_type``.
        frame: ``(M,)`` frame of each record, ordered.
        frames: number of rows.
        struct_type: the struct type (children are cast to its field types).
    """
    import pyarrow as pa

    # a child of the field's type as it is: a cast to the same type still costs a compute call
    # (most children are the input's own arrays, of the output's types)
    arrays = [c if c.type == fld.type else c.cast(fld.type)
              for fld in struct_type for c in (children[fld.name],)]  # fmt: skip
    struct = pa.StructArray.from_arrays(arrays, fields=list(struct_type))
    offsets = np.r_[0, np.cumsum(np.bincount(frame, minlength=frames))].astype(np.int32)
    return pa.ListArray.from_arrays(numpy_to_arrow(offsets), struct)


# ---------------------------------------------------------------------- reading
def open_log(path: str | Path, metadata: Any = None) -> Any:
    """Open a Parquet log for streaming; page checksums are verified where the file has them.

    Args:
        path: the file.
        metadata: the footer of the same file opened before (another reader of it, for another
            thread: a ``ParquetFile`` is not shared between threads); None: read it.

    Returns:
        A ``pyarrow.parquet.ParquetFile``. Reads are not pre-buffered: pre-buffering keeps every
        column chunk read so far, so memory would grow with the log.

    Raises:
        LogError: no such file, not a readable Parquet file, or a column of the log format with
            a type no reader can use (:func:`check_schema`) or null time stamps (where the
            file's statistics count them); the message names the file.
    """
    import pyarrow.parquet as pq

    if not Path(path).is_file():
        raise LogError(f"{path}: no such file")
    try:
        pf = pq.ParquetFile(
            path,
            metadata=metadata,
            pre_buffer=False,
            page_checksum_verification=True,
        )
    except Exception as exc:  # pyarrow raises ArrowInvalid, OSError, ...
        raise LogError(f"{path}: not a readable Parquet file ({exc})") from None
    check_schema(pf.schema_arrow, path)
    nulls = _null_stamps(pf)
    if nulls:
        raise LogError(
            f"{path}: {nulls} frames have no time stamp (null t_ns); every frame needs one"
        )
    return pf


def _null_stamps(pf: Any) -> int:
    """Null ``t_ns`` values the row groups' statistics count (0 without statistics)."""
    names = pf.schema_arrow.names
    if "t_ns" not in names:
        return 0
    meta = pf.metadata
    j = next((i for i in range(meta.num_columns) if meta.schema.column(i).path == "t_ns"), None)
    if j is None:
        return 0
    total = 0
    for g in range(meta.num_row_groups):
        st = meta.row_group(g).column(j).statistics
        if st is not None and st.has_null_count:
            total += st.null_count
    return total


def _unreadable(
    pf: Any,
    source: object,
    row: int,
    exc: Exception,
    columns: Sequence[str] | None = None,
    span: int = 0,
) -> LogError:
    """The error of a read of the rows ``[row, row + span)`` that failed.

    pyarrow reads a batch across row groups, so the damage may lie in a later group of the
    batch than ``row``'s: with ``columns``, the batch's groups are read one at a time (the
    columns the failed read asked for) and the first that fails is named, so that a read of the
    file in any batches or ranges names the same row group.
    """
    import pyarrow as pa

    starts = np.cumsum([0] + [pf.metadata.row_group(i).num_rows for i in range(pf.num_row_groups)])
    g = int(np.searchsorted(starts, row, side="right") - 1)
    g = min(max(g, 0), max(pf.num_row_groups - 1, 0))
    if columns is not None:
        end = int(np.searchsorted(starts, row + max(span, 1), side="left"))  # the batch's groups
        for k in range(g, min(max(end, g + 1), pf.num_row_groups)):
            try:
                pf.read_row_group(k, columns=list(columns))
            except (OSError, pa.ArrowException) as e:
                g, exc = k, e
                break
    lo, hi = int(starts[g]), int(starts[min(g + 1, len(starts) - 1)]) - 1

    if "Expected all lists to be of size" in str(exc) and int(pa.__version__.split(".")[0]) < 26:
        return LogError(
            f"{source}: row group {g} (rows {lo}-{hi}) has null entries in a fixed-size list"
            f" column, which pyarrow {pa.__version__} cannot read back ({exc}; apache/arrow#35692,"
            " fixed in pyarrow 26): pip install 'pyarrow>=26' (torchcontact now writes nullable"
            " vectors as variable-length lists, which any pyarrow reads)"
        )
    return LogError(
        f"{source}: corrupted data in row group {g} (rows {lo}-{hi}): {exc}; the file is damaged"
        " from there (a page checksum failed or a page did not decode)"
    )


def iter_chunks(
    pf: Any,
    columns: Sequence[str],
    batch_size: int,
    source: object = "",
    row_groups: Sequence[int] | None = None,
    exact: bool = True,
) -> Iterator[Any]:
    """Tables of exactly ``batch_size`` rows (the last one shorter), whatever the row groups.

    Args:
        pf: from :func:`open_log`.
        columns: columns to read.
        batch_size: rows per table (>= 1).
        source: file name for messages.
        row_groups: read only these consecutive row groups (default all).
        exact: False: the tables as read instead, at most ``batch_size`` rows each, cut at the
            row groups' ends (no copy to join them; for passes that need no fixed chunks).

    Yields:
        pyarrow tables, in file order.

    Raises:
        LogError: a page that fails its checksum or does not decode; the message names the row
            group and its rows. Tables before it were yielded.
    """
    import pyarrow as pa

    buf: list[Any] = []
    have = done = 0
    if row_groups is not None and len(row_groups):
        done = sum(pf.metadata.row_group(g).num_rows for g in range(row_groups[0]))
    kw = {} if row_groups is None else {"row_groups": list(row_groups)}
    it = pf.iter_batches(batch_size=batch_size, columns=list(columns), **kw)
    while True:
        try:
            rb = next(it, None)
        except (OSError, pa.ArrowException) as exc:
            raise _unreadable(pf, source, done + have, exc, columns, batch_size) from None
        if rb is None:
            break
        if not exact:
            yield pa.Table.from_batches([rb])
            done += rb.num_rows
            continue
        buf.append(rb)
        have += rb.num_rows
        while have >= batch_size:
            tab = pa.Table.from_batches(buf).combine_chunks()
            yield tab.slice(0, batch_size)
            done += batch_size
            rest = tab.slice(batch_size)
            buf, have = rest.to_batches(), rest.num_rows
    if have:
        yield pa.Table.from_batches(buf).combine_chunks()


def read_rows(path: str | Path, start: int, stop: int, columns: Sequence[str]) -> Any:
    """Rows ``[start, stop)`` of a log (only the row groups that hold them are read).

    Raises:
        LogError: an unreadable file, missing columns or rows outside the log.
    """
    import pyarrow as pa

    pf = open_log(path)
    missing = [c for c in columns if c not in pf.schema_arrow.names]
    if missing:
        raise LogError(f"{path}: missing columns {missing} (found {pf.schema_arrow.names})")
    n = pf.metadata.num_rows
    if not 0 <= start <= stop <= n:
        raise LogError(f"{path}: rows {start}-{stop - 1} are outside the log's {n} rows")
    sizes = [pf.metadata.row_group(g).num_rows for g in range(pf.num_row_groups)]
    bounds = np.cumsum([0, *sizes])
    groups = [g for g in range(len(sizes)) if bounds[g] < stop and bounds[g + 1] > start]
    try:
        tab = pf.read_row_groups(groups, columns=list(columns))
    except (OSError, pa.ArrowException) as exc:
        raise LogError(f"{path}: corrupted data ({exc})") from None
    first = int(bounds[groups[0]]) if groups else start
    return tab.slice(start - first, stop - start)


def read_log_columns(
    path: str | Path, columns: Sequence[str], *, joint_names: Sequence[str] | None = None
) -> dict[str, Any]:
    """Read columns of a log by name into numpy arrays (the whole file).

    Joint columns (``q``, ``qd``, ``qdd``, ``tau_measured``) are matched by joint name: with
    ``joint_names`` (e.g. ``model.joint_names``) they come in that order, the log's other joints
    left out; without it, in the log's order (:func:`joint_names_of`).

    Args:
        path: the log.
        columns: names: ``t_ns`` -> ``(N,)`` int64; a joint column -> ``(N, nv)``; ``ft.<s>`` ->
            ``(N, 6)``; ``base.*`` -> ``(N, 3)``; ``contacts`` ->
            :class:`~torchcontact.contacts.ContactRecords`; another list column -> ``(N, n)``; a
            numeric column -> ``(N,)`` float64. Rows that are null or of the wrong length are NaN.
        joint_names: the joint order wanted.

    Returns:
        ``{name: array}`` for every requested column.

    Raises:
        LogError: an unreadable file, a missing column or joint, no joint names in the metadata.

    Example:
        >>> import tempfile, pyarrow as pa
        >>> path = f"{tempfile.mkdtemp()}/log.parquet"
        >>> q = fixed_list(np.array([[1.0, 2.0]]))
        >>> _ = write_table(pa.table({"t_ns": [0], "q": q}).replace_schema_metadata(
        ...     {META_JOINT_NAMES: '["a", "b"]'}), path)
        >>> read_log_columns(path, ["q"], joint_names=["b", "a"])["q"].tolist()
        [[2.0, 1.0]]
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    pf = open_log(path)
    schema = pf.schema_arrow
    missing = [c for c in columns if c not in schema.names]
    if missing:
        raise LogError(f"{path}: missing columns {missing} (found {schema.names})")
    perm = None
    if any(c in JOINT_COLUMNS for c in columns):
        names = joint_names_of(schema, path)
        want = list(names) if joint_names is None else list(joint_names)
        absent = [n for n in want if n not in names]
        if absent:
            raise LogError(f"{path}: joints {absent} are not in the log (it has {names})")
        perm = np.array([names.index(n) for n in want], np.int64)
        nv = len(names)
    try:
        table = pf.read(columns=list(columns))
    except (OSError, pa.ArrowException) as exc:
        raise LogError(f"{path}: corrupted data ({exc})") from None
    out: dict[str, Any] = {}
    for c in columns:
        col = table.column(c)
        typ = schema.field(c).type
        if c == "t_ns":
            out[c] = timestamps(col, path)
        elif c == "contacts":
            out[c] = read_contacts(col)[0]
        elif c in JOINT_COLUMNS:
            out[c] = vectors(col, nv, c, path)[0][:, perm]
        elif c.startswith("ft."):
            out[c] = vectors(col, 6, c, path)[0]
        elif c in BASE_COLUMNS:
            out[c] = vectors(col, 3, c, path)[0]
        elif pa.types.is_fixed_size_list(typ):
            out[c] = vectors(col, typ.list_size, c, path)[0]
        elif pa.types.is_list(typ) or pa.types.is_large_list(typ):
            lengths = pc.list_value_length(col).drop_null()
            out[c] = vectors(col, int(lengths[0].as_py()) if len(lengths) else 0, c, path)[0]
        else:
            check_number_type(typ, c, path)
            out[c] = arrow_to_numpy(_float64(one_array(col)), np.float64)
    return out


def timestamps(column: Any, source: object = "", first_row: int = 0) -> np.ndarray:
    """A ``t_ns`` column as ``(N,)`` int64 ns (integers of any width, or time stamps of any unit).

    Args:
        column: the Arrow column.
        source: the file, for messages.
        first_row: the file row of the column's first value, for messages.

    Raises:
        LogError: a type other than integers or time stamps, or null time stamps (naming the
            first row).

    Example:
        >>> import pyarrow as pa
        >>> timestamps(pa.array([0, 10], pa.int32())).tolist()
        [0, 10]
        >>> timestamps(pa.array([1, 2], pa.timestamp("us"))).tolist()
        [1000, 2000]
    """
    import pyarrow as pa

    column = one_array(column)
    where = f"{source}: " if str(source) else ""
    typ = column.type
    if not (pa.types.is_integer(typ) or pa.types.is_timestamp(typ)):
        raise LogError(f"{where}column 't_ns' is {typ}; expected int64 time stamps (ns)")
    if column.null_count:
        first = int(np.flatnonzero(arrow_to_numpy(column.is_null()))[0])
        raise LogError(
            f"{where}{column.null_count} frames have no time stamp (null t_ns), the first in row"
            f" {first_row + first}; every frame needs one"
        )
    if pa.types.is_timestamp(typ):  # any unit -> ns since the epoch
        column = column.cast(pa.timestamp("ns", typ.tz))
    try:
        ints = column.cast(pa.int64())
    except pa.ArrowInvalid as exc:  # uint64 beyond int64
        raise LogError(f"{where}column 't_ns' ({typ}) does not fit int64 ns: {exc}") from None
    return arrow_to_numpy(ints, np.int64)


# ---------------------------------------------------------------------- writing
def _tmp(path: Path) -> Path:
    return path.with_name(path.name + ".tmp")


class LogWriter:
    """Write a Parquet log in parts: page checksums, a temporary name, an atomic rename on close.

    Args:
        path: the final file; ``<path>.tmp`` holds the data until :meth:`close`.
        schema: the pyarrow schema (with its metadata).
        unique_tmp: a temporary name of this writer's own (``<path>.<pid>-<random>.tmp``), for
            files that two writers may write at once (a run's part, which a Ray worker left by a
            killed driver may still be writing while the resumed run writes it again): the
            last rename wins, and no file mixes the two.
        create_dirs: create ``path``'s folder when missing (False: a missing folder is an
            error, for a run's part whose run has ended and removed its folder).

    Example:
        >>> import tempfile, pyarrow as pa
        >>> path = Path(tempfile.mkdtemp()) / "log.parquet"
        >>> with LogWriter(path, ft_log_schema("s")) as w:
        ...     w.write(pa.table({"t_ns": [1], "ft.s": fixed_list(np.zeros((1, 6)))}))
        >>> path.exists(), w.rows
        (True, 1)
    """

    def __init__(
        self, path: str | Path, schema: Any, unique_tmp: bool = False, create_dirs: bool = True
    ) -> None:
        self.path = Path(path)
        self.schema = schema
        self.rows = 0
        self._writer: Any = None
        self._create_dirs = create_dirs
        self._tmp = _tmp(self.path)
        if unique_tmp:
            import uuid

            self._tmp = self.path.with_name(
                f"{self.path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp"
            )

    def write(self, table: Any, row_group_size: int | None = None) -> None:
        """Append a table (or record batch) cast to the schema."""
        import pyarrow.parquet as pq

        if self._writer is None:
            if self._create_dirs:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            stats = ["t_ns"] if "t_ns" in self.schema.names else False
            self._writer = pq.ParquetWriter(
                self._tmp, self.schema, write_statistics=stats, **WRITE_OPTIONS
            )
        table = _conformed(table, self.schema)
        self._writer.write_table(table, row_group_size=row_group_size)
        self.rows += table.num_rows

    def close(self) -> None:
        """Finish the file and rename it to its final name (an empty log keeps its schema)."""
        if self._writer is None:
            self.write(self.schema.empty_table())
        self._writer.close()
        self._writer = None
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        """Drop the temporary file; the final name is left untouched."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _conformed(table: Any, schema: Any) -> Any:
    """``table`` as a table of ``schema`` (its metadata, its types: cast only when they differ)."""
    import pyarrow as pa

    if isinstance(table, pa.RecordBatch):
        table = pa.Table.from_batches([table])
    if table.schema.equals(schema, check_metadata=True):
        return table  # an estimate's own table: the cast would copy nothing but cost 15 %
    return table.replace_schema_metadata(schema.metadata).cast(schema)


# ---------------------------------------------------------------------- a log written in parts
@dataclass(frozen=True)
class EncodedPart:
    """A table encoded as the row groups of a Parquet log, not yet placed in a file.

    Attributes:
        data: the column chunks (the bytes between ``PAR1`` and the footer of the part's own
            file).
        footer: that file's footer (Thrift ``FileMetaData``), offsets counted from its start.
        rows: the table's rows.
    """

    data: Any
    footer: bytes
    rows: int


def encode_part(table: Any, schema: Any) -> EncodedPart:
    """Encode a table (or record batch) as a part of a log (:class:`PartsWriter`).

    The options, checksums and statistics of :class:`LogWriter`, one row group per million rows
    (pyarrow's default), as :meth:`LogWriter.write` would write it. The encoding releases the
    GIL: several parts may be encoded at once on several threads.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from torchcontact.logs._footer import split_file

    table = _conformed(table, schema)
    sink = pa.BufferOutputStream()
    stats = ["t_ns"] if "t_ns" in schema.names else False
    with pq.ParquetWriter(sink, schema, write_statistics=stats, **WRITE_OPTIONS) as w:
        w.write_table(table)
    data, footer = split_file(memoryview(sink.getvalue()))
    return EncodedPart(data, bytes(footer), table.num_rows)


@dataclass(frozen=True)
class PartIndex:
    """Where a part lies in the file :class:`PartsWriter` writes (a journal entry of a run).

    Attributes:
        start: byte offset of its column chunks.
        size: their length in bytes.
        rows: its rows.
        footer: the footer of the part's own file (:class:`EncodedPart`).
    """

    start: int
    size: int
    rows: int
    footer: bytes

    @property
    def end(self) -> int:
        """The byte after the part."""
        return self.start + self.size


class PartsWriter:
    """Write a Parquet log part by part, each part's bytes final as soon as it is appended.

    The file ``<path>.tmp`` is ``PAR1`` and the parts' column chunks one after the other; the
    footer, joined from the parts' own footers (:mod:`torchcontact.logs._footer`), is written by
    :meth:`close`, which then renames the file to ``path``. The result is the file
    :class:`LogWriter` writes from the same tables, byte for byte. Since a part never changes once
    appended, a run interrupted at any point (``kill -9`` included) can keep the parts it recorded
    (their :class:`PartIndex`) and go on appending after them (``done``).

    Args:
        path: the final file.
        schema: the pyarrow schema (with its metadata).
        done: the parts already in ``<path>.tmp`` (a resumed run), in order; the file is cut
            after the last one (bytes of a part that was not recorded go).

    Raises:
        LogError: ``<path>.tmp`` does not hold the ``done`` parts (shorter, or not a log's start).
    """

    def __init__(self, path: str | Path, schema: Any, done: Sequence[PartIndex] = ()) -> None:
        from torchcontact.logs._footer import MAGIC, FooterJoin

        self.path = Path(path)
        self.tmp = _tmp(self.path)
        self.schema = schema
        self.parts: list[PartIndex] = list(done)
        self.rows = sum(p.rows for p in self.parts)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.parts:
            end = self.parts[-1].end
            size = self.tmp.stat().st_size if self.tmp.is_file() else -1
            if size < end:
                raise LogError(f"{self.tmp}: shorter ({size} bytes) than its journal ({end} bytes)")
            self._file = open(self.tmp, "r+b", buffering=0)
            if self._file.read(4) != MAGIC:
                self._file.close()
                raise LogError(f"{self.tmp}: not the start of a Parquet log")
            self._file.truncate(end)
            self._file.seek(end)
        else:
            self._file = open(self.tmp, "wb", buffering=0)
            self._file.write(MAGIC)
        self.position = self.parts[-1].end if self.parts else len(MAGIC)
        # the footer is joined as the parts come (on the appending thread), not all at close
        self._join = FooterJoin()
        for p in self.parts:
            self._join.add(p.start, p.footer)

    def append(self, part: EncodedPart) -> PartIndex:
        """Append an encoded part; returns where it lies (handed to the OS when this returns)."""
        return self.append_many([part])[0]

    def append_many(self, parts: Sequence[EncodedPart], pool: Any = None) -> list[PartIndex]:
        """Append parts one after the other, their bytes written at once on ``pool``'s threads.

        Each part's place follows from the sizes of those before it, so the parts' bytes are
        written at their offsets in parallel (``os.pwrite``; the kernel copies and the GIL is
        released), then recorded in order as :meth:`append` records one. A Ray driver appends
        the parts that its workers finished together this way (at the end of a run, the last
        unit of every worker): one part's copy took 27-40 ms on the 2-core machine.

        Args:
            parts: the parts, in file order.
            pool: a ``concurrent.futures`` executor (None, or a single part: written here).

        Returns:
            Where each part lies, as :meth:`append` returns it.
        """
        starts, at = [], self.position
        for part in parts:
            starts.append(at)
            at += len(memoryview(part.data))
        fd = self._file.fileno()

        def put(part: EncodedPart, start: int) -> None:
            view = memoryview(part.data)
            done = 0
            while done < len(view):  # a write may write less than asked
                done += os.pwrite(fd, view[done:], start + done)

        if pool is None or len(parts) < 2:
            for part, start in zip(parts, starts, strict=True):
                put(part, start)
        else:
            writes = [pool.submit(put, p, at) for p, at in zip(parts, starts, strict=True)]
            for f in writes:
                f.result()
        self._file.seek(at)
        out = []
        for part, start in zip(parts, starts, strict=True):
            self._join.add(start, part.footer)  # its row groups shifted to where they lie
            index = PartIndex(start, len(memoryview(part.data)), part.rows, part.footer)
            self.position = index.end
            self.parts.append(index)
            self.rows += part.rows
            out.append(index)
        return out

    def close(self) -> None:
        """Write the joined footer and rename the file (an empty log keeps its schema)."""
        from torchcontact.logs._footer import footer_bytes

        if not self.parts:
            self.append(encode_part(self.schema.empty_table(), self.schema))
        self._file.write(footer_bytes(self._join.footer()))
        self._file.close()
        os.replace(self.tmp, self.path)

    def abort(self, keep: bool = False) -> None:
        """Close the file; drop it unless ``keep`` (its parts are kept for a resume)."""
        if not self._file.closed:
            self._file.close()
        if not keep:
            self.tmp.unlink(missing_ok=True)


def write_encoded_part(tables: Iterable[Any], path: str | Path, schema: Any) -> Path:
    """A unit's tables as a Parquet file of its own: a Ray worker's part of a run's output.

    The options of :class:`LogWriter`, one row group per table (as :func:`encode_part` encodes
    one chunk), a temporary name of its own and an atomic rename: a worker of a killed driver
    (a pool actor outlives it) may still write the part the resumed run writes again, and the
    last rename wins with the same bytes. The folder is not created: once the run has ended and
    removed it, such a late write fails instead of leaving a stray folder. The driver appends
    the file's column chunks to the output as they are (:func:`read_encoded_part`,
    :meth:`PartsWriter.append`): the workers encode in parallel, the driver copies bytes.

    Raises:
        InputError: no table.
        FileNotFoundError: ``path``'s folder is gone (its run has ended).
    """
    with LogWriter(path, schema, unique_tmp=True, create_dirs=False) as w:
        n = 0
        for tab in tables:
            w.write(tab)
            n += 1
        if n == 0:
            raise InputError(f"{path}: a part needs at least one table")
    return Path(path)


def read_encoded_part(path: str | Path) -> tuple[EncodedPart, Any]:
    """The :class:`EncodedPart` of a file :func:`write_encoded_part` wrote, and its bytes.

    Returns:
        ``(part, buffer)``: the part to append (its column chunks a view of the file's bytes,
        not a copy), and the whole file as a pyarrow buffer (:func:`encoded_part_table`).

    Raises:
        LogError: the file is not a whole Parquet file.
    """
    import pyarrow as pa

    from torchcontact.logs._footer import FooterError, footer_rows, split_file

    try:
        data = Path(path).read_bytes()
        chunks, footer = split_file(memoryview(data))
        rows = footer_rows(bytes(footer))
    except (OSError, FooterError) as exc:
        raise LogError(f"{path}: unreadable part of a run ({exc})") from None
    return EncodedPart(chunks, bytes(footer), rows), pa.py_buffer(data)


def encoded_part_table(buffer: Any, path: str | Path, columns: Sequence[str] | None = None) -> Any:
    """Columns of a part's file from its bytes (:func:`read_encoded_part`), checksums verified.

    Args:
        buffer: the file's bytes (a pyarrow buffer).
        path: the file, for messages.
        columns: the columns to read (default: every column).

    Raises:
        LogError: the part is damaged.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        # ParquetFile, not pq.read_table: the dataset reader imports pandas
        f = pq.ParquetFile(pa.BufferReader(buffer), page_checksum_verification=True)
        return f.read(columns=columns)
    except (OSError, pa.ArrowException) as exc:
        raise LogError(f"{path}: unreadable part of a run ({exc})") from None


def write_table(table: Any, path: str | Path, row_group_size: int | None = None) -> Path:
    """Write a whole table to ``path`` (page checksums, temporary name, atomic rename)."""
    with LogWriter(path, table.schema) as w:
        w.write(table, row_group_size=row_group_size)
    return Path(path)


# ---------------------------------------------------------------------- journal of a run
def write_journal(tables: Iterator[Any] | Sequence[Any], path: str | Path) -> Path:
    """Write tables as one journal part: an Arrow IPC file (lz4), temporary name, atomic rename.

    The journal holds the estimated chunks of a run that is still going; a resumed run reads it
    back (:func:`read_journal`) instead of estimating them again. It is never a log.
    """
    import pyarrow as pa

    path = Path(path)
    tmp = _tmp(path)
    writer = None
    try:
        for tab in tables:
            if writer is None:
                options = pa.ipc.IpcWriteOptions(compression="lz4")
                writer = pa.ipc.new_file(tmp, tab.schema, options=options)
            writer.write_table(tab)
        if writer is None:
            raise InputError(f"{path}: a journal part needs at least one table")
        writer.close()
    except BaseException:
        if writer is not None:
            writer.close()
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
    return path


def write_part_index(index: PartIndex, path: str | Path) -> Path:
    """Record where a part of a run's output lies: a journal entry (temporary name, rename).

    The entry is a JSON line (``start``, ``size``, ``rows``) and the part's footer; it is written
    after the part's bytes were handed to the OS, so an entry always describes bytes that exist.
    """
    path = Path(path)
    tmp = _tmp(path)
    head = json.dumps({"start": index.start, "size": index.size, "rows": index.rows})
    try:
        with open(tmp, "wb") as f:
            f.write(head.encode() + b"\n" + index.footer)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def read_part_index(path: str | Path) -> PartIndex:
    """A journal entry written by :func:`write_part_index`.

    Raises:
        LogError: an unreadable entry.
    """
    try:
        data = Path(path).read_bytes()
        head, footer = data.split(b"\n", 1)
        rec = json.loads(head)
        return PartIndex(int(rec["start"]), int(rec["size"]), int(rec["rows"]), footer)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise LogError(f"{path}: unreadable part of an interrupted run ({exc})") from None


def read_part(path: str | Path, index: PartIndex) -> Any:
    """The table of one part of a file :class:`PartsWriter` writes (page checksums verified).

    Raises:
        LogError: the part cannot be read back (a damaged file).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from torchcontact.logs._footer import standalone

    try:
        with open(path, "rb") as f:
            f.seek(index.start)
            data = f.read(index.size)
        if len(data) != index.size:
            raise OSError(f"{len(data)} of {index.size} bytes")
        buf = pa.BufferReader(standalone(data, index.footer))
        return pq.ParquetFile(buf, page_checksum_verification=True).read()  # no pandas
    except (OSError, ValueError, pa.ArrowException) as exc:
        raise LogError(
            f"{path}: the part at byte {index.start} of an interrupted run is unreadable ({exc})"
        ) from None


def read_journal(path: str | Path) -> Any:
    """The table of a journal part written by :func:`write_journal`.

    Raises:
        LogError: an unreadable part.
    """
    import pyarrow as pa

    try:
        with pa.ipc.open_file(path) as f:
            return f.read_all()
    except (OSError, pa.ArrowException) as exc:
        raise LogError(f"{path}: unreadable part of an interrupted run ({exc})") from None


def expand_inputs(inputs: Sequence[str | Path]) -> list[Path]:
    """Files, folders (their ``*.parquet``) and globs -> a sorted list of files.

    Raises:
        LogError: an input that matches nothing.
    """
    files: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = sorted(p.glob("*.parquet"))
        elif p.exists():
            found = [p]
        else:
            found = sorted(Path(m) for m in glob.glob(str(item)))
        if not found:
            raise LogError(f"{item}: no such file, folder or glob match")
        files += found
    return files


def output_paths(inputs: Sequence[Path], out: str | Path) -> list[Path]:
    """Output file per input: ``out`` itself for one file, ``out/<name>`` for several."""
    out = Path(out)
    if len(inputs) == 1 and not out.is_dir():
        return [out]
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: several inputs need a folder, and {out} is a file")
    names = [p.name for p in inputs]
    if len(set(names)) != len(names):
        raise LogError(f"inputs share file names {names}; give them distinct names")
    return [out / n for n in names]


def check_outputs(
    outputs: Sequence[str | Path], inputs: Sequence[str | Path | None], option: str = "--out"
) -> None:
    """Refuse an output that is, or contains, one of the inputs (nothing is written).

    Args:
        outputs: every path a command will write or replace (files, side files, folders).
        inputs: every path it reads (None entries are skipped).
        option: the option naming the output, for the message.

    Raises:
        InputError: an output that is an input (same path, or the same file through a link), or
            a folder output that holds an input.
    """
    ins = [Path(i) for i in inputs if i is not None]
    for o in map(Path, outputs):
        o_abs, o_res = o.absolute(), o.resolve()
        for i in ins:
            i_abs, i_res = i.absolute(), i.resolve()
            same = o_abs == i_abs or o_res == i_res
            if not same and o.exists() and i.exists():
                same = os.path.samefile(o, i)
            if same:
                raise InputError(
                    f"{option} {o} is the input {i}: refusing to overwrite it; choose another"
                    " output (nothing was written)"
                )
            if i_res.is_relative_to(o_res) or i_abs.is_relative_to(o_abs):
                raise InputError(
                    f"{option} {o} contains the input {i}: refusing to write there; choose"
                    " another output (nothing was written)"
                )
