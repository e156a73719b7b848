"""Decoding a log for estimation: its schema, a first pass over the file, each chunk as arrays.

Three steps, each on the data's way from Parquet to the estimator:

1. :func:`log_columns`: the schema checked against the robot (joints, sensors, the contact
   struct, derived ``qd``/``qdd``, the columns to read).
2. :func:`scan_log`: two passes over the cheap columns of the whole file (``t_ns`` and the
   contacts' ``link`` and ``kind`` only): the most records of each ``(link, kind)`` pair in one
   frame, which fixes **one slot layout for the whole log** (so every chunk runs the same
   compiled program), and the time steps and segments (:mod:`torchcontact.logs.derive`).
3. :class:`ChunkDecoder`: a chunk's Arrow columns -> numpy arrays in the model's joint order, the
   contact records checked and placed in the log's slots, and each frame's problems as status
   bits with a detail text (:class:`FrameIssues`). No Python loop runs per frame or per record:
   loops run over the distinct link names, kinds and messages only.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torchcontact.contacts import KINDS, ContactRecords, Contacts, SlotLayout
from torchcontact.errors import InputError, LogError
from torchcontact.logs.derive import (
    GAP_FACTOR,
    MIN_SEGMENT_FRAMES,
    median_step,
    step_histogram,
    time_segments,
)
from torchcontact.logs.format import (
    BASE_COLUMNS,
    arrow_scalar,
    arrow_to_numpy,
    ft_column,
    ft_cov_column,
    iter_chunks,
    joint_names_of,
    numpy_to_arrow,
    one_array,
    read_contacts,
    string_array,
    timestamps,
    vectors,
)
from torchcontact.model import RobotModel
from torchcontact.status import Status, status_messages

__all__ = [
    "NOT_DIFFERENTIABLE",
    "ChunkDecoder",
    "Decoded",
    "FrameIssues",
    "LogColumns",
    "LogScan",
    "log_columns",
    "scan_log",
    "scan_rest",
    "scan_step",
    "scan_threads",
    "status_text",
]

#: Status bit of a frame whose ``qd``/``qdd`` cannot be derived (its time segment is too short).
NOT_DIFFERENTIABLE = int(Status.NOT_DIFFERENTIABLE)

#: Frames per block of the first pass (:func:`scan_log`).
SCAN_BLOCK = 1 << 16


# ---------------------------------------------------------------------- the schema
@dataclass(frozen=True)
class LogColumns:
    """What a log's schema gives an estimate.

    Attributes:
        joint_names: joint order of ``q`` (schema metadata).
        sensors: sensors to use.
        derived: ``qd``/``qdd`` missing from the log (derived from ``q``).
        contact_fields: ``(name, type)`` fields of the contact struct (empty: no contacts).
        columns: the columns a chunk reads.
    """

    joint_names: list[str]
    sensors: list[str]
    derived: list[str]
    contact_fields: list[tuple[str, Any]]
    columns: list[str]


def _sensors_of(schema: Any, model: RobotModel, sensors: Sequence[str] | None, src: str) -> list:
    cols = [n for n in schema.names if n.startswith("ft.")]
    if sensors:
        missing = [s for s in sensors if ft_column(s) not in cols]
        if missing:
            raise LogError(f"{src}: no column for sensors {missing} (found {cols})")
        return list(sensors)
    found = [c[3:] for c in cols if c[3:] in model.ft_sensors]
    if not found:
        raise LogError(
            f"{src}: no ft.<sensor> column for the robot's sensors {list(model.ft_sensors)}"
            f" (found {cols})"
        )
    return found


def log_columns(
    schema: Any,
    model: RobotModel,
    src: str,
    sensors: Sequence[str] | None = None,
    constraints: Any = None,
    extra_columns: Sequence[str] = (),
    localize: bool = False,
) -> LogColumns:
    """Check a log's schema and list what an estimate reads from it.

    A log without a ``contacts`` column is estimated as contact-free, with one warning (none when
    its contacts are localized: ``localize``).

    Args:
        schema: the log's Arrow schema.
        model: the robot.
        src: file name for messages.
        sensors: sensors to use (default: those with a column).
        constraints: a :class:`~torchcontact.logs.LogConstraints` or None.
        extra_columns: further columns needed (a residual's features, e.g. ``temperature``).
        localize: the contacts are localized from the F/T readings (``estimate --localize``).

    Raises:
        LogError: no ``t_ns`` or ``q``, no joint names, no sensor column, a contacts column that
            is not a list of structs with ``link``, ``kind`` and ``position``, a missing extra
            column.
        InputError: ``constraints`` on contacts without ``normal``, or without ``friction`` /
            ``cone_angle`` and no default friction.
    """
    import pyarrow as pa

    for col in ("t_ns", "q"):
        if col not in schema.names:
            raise LogError(f"{src}: missing column {col!r} (found {schema.names})")
    joint_names = joint_names_of(schema, src)
    used = _sensors_of(schema, model, sensors, src)
    derived = [c for c in ("qd", "qdd") if c not in schema.names]
    contact_fields: list[tuple[str, Any]] = []
    if "contacts" in schema.names:
        ctype = schema.field("contacts").type
        if not (pa.types.is_list(ctype) or pa.types.is_large_list(ctype)) or not pa.types.is_struct(
            ctype.value_type
        ):
            raise LogError(f"{src}: contacts must be a list of structs, found {ctype}")
        contact_fields = [(f.name, f.type) for f in ctype.value_type]
        names = [n for n, _ in contact_fields]
        for need in ("link", "kind", "position"):
            if need not in names:
                raise LogError(f"{src}: contact struct lacks field {need!r} (has {names})")
    elif not localize:
        warnings.warn(
            f"{src}: no 'contacts' column: every frame is estimated as contact-free (any contact"
            " load shows in residual.<sensor>)",
            UserWarning,
            stacklevel=3,
        )
    if constraints is not None and contact_fields:
        names = [n for n, _ in contact_fields]
        if "normal" not in names:
            raise InputError(
                f"--constraints: the contacts of {src} have no 'normal' field (outward surface"
                f" normal, link frame); found {names}"
            )
        if constraints.friction is None and not {"friction", "cone_angle"} & set(names):
            raise InputError(
                f"--constraints: the contacts of {src} have no friction or cone_angle field;"
                " give a default with --friction or --cone-angle"
            )
    for col in extra_columns:
        if col not in schema.names:
            raise LogError(
                f"{src}: the residual checkpoint needs column {col!r}, which the log lacks"
                f" (found {schema.names})"
            )
    columns = ["t_ns", "q", *[c for c in ("qd", "qdd") if c in schema.names]]
    columns += [ft_column(s) for s in used]
    columns += [c for c in ("tau_measured", *BASE_COLUMNS, "contacts") if c in schema.names]
    columns += [c for c in extra_columns if c not in columns]
    return LogColumns(joint_names, used, derived, contact_fields, columns)


# ---------------------------------------------------------------------- first pass
@dataclass(frozen=True)
class LogScan:
    """What one pass over a log's ``t_ns`` and contact names finds.

    Attributes:
        rows: frames of the log.
        pairs: ``{(link, kind): most records of that pair in one frame}`` over the whole log.
        step_ns: median step of ``t_ns`` (positive steps, to the microsecond), ns; 0 if none.
        segments: time segments (:func:`~torchcontact.logs.derive.time_segments`).
        repeats: frames whose stamp repeats or runs backward (each a segment of its own).
        gaps: segment starts at a gap over ``GAP_FACTOR`` median steps.
        short_frames: frames in segments of fewer than ``MIN_SEGMENT_FRAMES`` frames (they
            cannot be differentiated when ``qd``/``qdd`` are derived).
    """

    rows: int
    pairs: dict[tuple[str, str], int] = field(default_factory=dict)
    step_ns: float = 0.0
    segments: int = 1
    repeats: int = 0
    gaps: int = 0
    short_frames: int = 0

    def layout(self, usable: Any = None) -> SlotLayout:
        """The log's slot layout: per usable ``(link, kind)`` pair (sorted), its most records.

        Args:
            usable: ``usable(link, kind) -> bool`` (default: every known kind): pairs no frame
                can use (an unknown link) get no slot.
        """
        links: list[str] = []
        kinds: list[str] = []
        for (link, kind), m in sorted(self.pairs.items()):
            if kind in KINDS and (usable is None or usable(link, kind)):
                links += [link] * m
                kinds += [kind] * m
        return SlotLayout(tuple(links), tuple(kinds))

    def describe_time(self) -> str:
        """One sentence on the log's time segments (for the warning of a derived log)."""
        causes = []
        if self.repeats:
            causes.append(f"{self.repeats} frames with a repeated or backward t_ns")
        if self.gaps:
            causes.append(
                f"{self.gaps} gaps over {GAP_FACTOR:g} x the median step {self.step_ns / 1e6:g} ms"
            )
        return (
            f"t_ns splits into {self.segments} time segments ({', '.join(causes)}): qd/qdd are"
            f" derived within each segment; {self.short_frames} frames lie in segments of fewer"
            f" than {MIN_SEGMENT_FRAMES} frames and cannot be differentiated (status"
            f" {NOT_DIFFERENTIABLE})"
        )


def _name_leaf(pf: Any, name: str) -> str | None:
    """The Parquet column path of the contacts' ``name`` field (``contacts.list.element.link``)."""
    meta = pf.metadata
    for i in range(meta.num_columns):
        path = meta.schema.column(i).path
        parts = path.split(".")
        if parts[0] == "contacts" and len(parts) == 4 and parts[-1] == name:
            return path
    return None


def _pair_counts(lst: Any, names: dict[str, int], into: dict[tuple[int, int], int]) -> None:
    """Most records of each ``(link, kind)`` in one frame of a ``list<struct<link, kind>>``."""
    import pyarrow as pa
    import pyarrow.compute as pc

    lst = one_array(lst)
    if lst.null_count:  # null rows -> empty lists, as read_contacts
        lst = pc.if_else(lst.is_null(), arrow_scalar([], lst.type), lst)
    structs = lst.flatten()
    if not len(structs):
        return
    frame = arrow_to_numpy(pc.list_parent_indices(lst), np.int64)
    codes = []
    for key in ("link", "kind"):
        enc = structs.field(key)
        if not pa.types.is_dictionary(enc.type):  # strings (a log may store dictionary arrays)
            enc = pc.dictionary_encode(enc)
        gid = np.array([names.setdefault(str(v), len(names)) for v in enc.dictionary.to_pylist()]
                       + [-1], np.int64)  # fmt: skip
        codes.append(gid[arrow_to_numpy(enc.indices, np.int64, fill=len(gid) - 1)])
    ok = (codes[0] >= 0) & (codes[1] >= 0)
    if not ok.any():
        return
    base = len(names) + 1
    pair = codes[0][ok] * base + codes[1][ok]
    fr = frame[ok] - frame[0]  # frames of the block from 0 (list_parent_indices ascend)
    # records per frame of each pair present (a few pairs: counting, not sorting, the records)
    for u in np.flatnonzero(np.bincount(pair)).tolist():
        m = int(np.bincount(fr[pair == u]).max())
        pk = (u // base, u % base)
        into[pk] = max(into.get(pk, 0), m)


def scan_log(pf: Any, src: str, contacts: bool, threads: int = 1) -> LogScan:
    """Two passes over the cheap columns of the whole log: ``t_ns``, the contacts' names.

    :func:`scan_step` then :func:`scan_rest` (the second pass needs the median step).

    Args:
        pf: the opened log (:func:`~torchcontact.logs.format.open_log`).
        src: the log's path (named in messages; opened again by each thread).
        contacts: the log has a ``contacts`` column.
        threads: threads of each pass (:func:`scan_threads`).

    Returns:
        :class:`LogScan`.

    Raises:
        LogError: ``t_ns`` of another type or with nulls, unreadable data (the message names
            the row group).
    """
    return scan_rest(pf, src, contacts, scan_step(pf, src, threads), threads)


#: Most threads of a scan pass.
SCAN_THREADS = 8
#: Rows of a log per scan thread at least.
SCAN_ROWS_PER_THREAD = 1 << 19


def scan_threads(rows: int) -> int:
    """Threads for the scan passes of a log of ``rows`` frames.

    Each thread reads a range of consecutive row groups with a reader of its own (pyarrow reads
    and decodes without the GIL). Half the cores at most, so one on a 2-core machine, where the
    scan's second pass already runs beside the noise estimate; up to :data:`SCAN_THREADS` on a
    many-core driver, where the scan of a long log is what the Ray workers wait for.

    Example:
        >>> scan_threads(1000) == 1
        True
    """
    import os

    cores = os.cpu_count() or 1
    return max(1, min(SCAN_THREADS, cores // 2, rows // SCAN_ROWS_PER_THREAD))


def _ranges(pf: Any, parts: int) -> list[tuple[int, int, int]]:
    """At most ``parts`` ranges of consecutive row groups of about equal rows.

    Returns:
        ``(first group, end group, first row)`` of each range, in file order.
    """
    meta = pf.metadata
    sizes = [meta.row_group(g).num_rows for g in range(meta.num_row_groups)]
    if not sizes:
        return [(0, 0, 0)]
    bounds = np.cumsum([0, *sizes])
    parts = max(1, min(parts, len(sizes)))
    cuts = np.searchsorted(bounds, np.linspace(0, bounds[-1], parts + 1)[1:-1])
    edges = sorted({0, *(int(c) for c in cuts), len(sizes)})
    return [(a, b, int(bounds[a])) for a, b in zip(edges, edges[1:], strict=False) if b > a]


def _map_ranges(pf: Any, src: str, threads: int, fn: Any) -> list[Any]:
    """``fn(reader, first group, end group, first row)`` over the ranges of :func:`_ranges`.

    On this thread with ``pf`` for one range, else on a thread each with a reader of its own (a
    ``ParquetFile`` is not shared between threads). Results in file order; the first range's
    error in file order is raised, as a pass in order would raise it.
    """
    ranges = _ranges(pf, threads)
    if len(ranges) == 1:
        return [fn(pf, *ranges[0])]
    from concurrent.futures import ThreadPoolExecutor

    from torchcontact.logs.format import open_log

    def one(r: tuple[int, int, int]) -> Any:
        return fn(open_log(src, pf.metadata), *r)

    with ThreadPoolExecutor(len(ranges), thread_name_prefix="torchcontact-scan") as pool:
        futures = [pool.submit(one, r) for r in ranges]
        return [f.result() for f in futures]


def scan_step(pf: Any, src: str, threads: int = 1) -> float:
    """The first pass: the median step of the log's ``t_ns`` (:func:`median_step`), ns.

    Every stamp is checked here (type, nulls), before any chunk is decoded. With ``threads``,
    ranges of row groups are read at once and their step histograms added (the steps across the
    ranges' edges too): the same median.

    Raises:
        LogError: ``t_ns`` of another type or with nulls, unreadable ``t_ns`` data.
    """

    def one(reader: Any, g0: int, g1: int, row0: int) -> tuple[dict, int | None, int | None]:
        hist: dict[int, int] = {}
        first = last = None
        done = row0
        for tab in iter_chunks(reader, ["t_ns"], SCAN_BLOCK, src, range(g0, g1), exact=False):
            t = timestamps(tab.column("t_ns"), src, done)
            if len(t):
                step_histogram(t if last is None else np.r_[last, t], hist)
                first = int(t[0]) if first is None else first
                last = int(t[-1])
            done += tab.num_rows
        return hist, first, last

    hist: dict[int, int] = {}
    last = None
    for part, first, end in _map_ranges(pf, src, threads, one):
        for k, c in part.items():
            hist[k] = hist.get(k, 0) + c
        if first is not None:
            if last is not None:  # the step across the ranges' edge
                step_histogram(np.array([last, first], np.int64), hist)
            last = end
    return median_step(hist)


@dataclass
class _RestPart:
    """One range's share of the second pass (merged in file order by :func:`scan_rest`)."""

    pairs: dict[tuple[str, str], int]
    untrusted: int = 0
    gaps: int = 0
    starts: int = 0  # segment starts in the range
    first_start: int = 0  # row of the first of them
    last_start: int = 0  # row of the last of them
    short_inside: int = 0  # frames of the short segments between the range's starts


def _stamps_before(pf: Any, src: str, group: int) -> np.ndarray:
    """The last two stamps before row group ``group`` (fewer at the log's start)."""
    t = np.zeros(0, np.int64)
    g = group
    while len(t) < 2 and g > 0:
        g -= 1
        row0 = sum(pf.metadata.row_group(i).num_rows for i in range(g))
        n = pf.metadata.row_group(g).num_rows
        for tab in iter_chunks(pf, ["t_ns"], max(n, 1), src, [g]):
            t = np.r_[timestamps(tab.column("t_ns"), src, row0), t]
    return t[-2:]


def scan_rest(pf: Any, src: str, contacts: bool, step: float, threads: int = 1) -> LogScan:
    """The second pass: time segments at the median ``step`` and the contacts' ``(link, kind)``.

    Reads ``t_ns`` and the contacts' ``link`` and ``kind`` only. It needs nothing decoded, so a
    run can do it on a thread of its own, beside the chunks it decodes first
    (:func:`torchcontact.logs.pipeline.open_prepared`). With ``threads``, ranges of row groups
    are read at once, each with the two stamps before it as context, and merged in file order:
    the same result.

    Raises:
        LogError: unreadable data (the message names the row group).
    """
    rows = pf.metadata.num_rows
    leaves = [_name_leaf(pf, n) for n in ("link", "kind")] if contacts else []
    if contacts and None in leaves:  # an unusual nesting: read the whole column
        leaves = ["contacts"]

    def one(reader: Any, g0: int, g1: int, row0: int) -> _RestPart:
        names: dict[str, int] = {}
        counts: dict[tuple[int, int], int] = {}
        part = _RestPart({})
        ctx = _stamps_before(reader, src, g0)  # the last two stamps before the range
        prev = None  # the range's last segment start so far
        done = row0
        cols = ["t_ns", *leaves]
        for tab in iter_chunks(reader, cols, SCAN_BLOCK, src, range(g0, g1), exact=False):
            t = timestamps(tab.column("t_ns"), src, done)
            if not len(t):
                continue
            if contacts:
                _pair_counts(tab.column("contacts"), names, counts)
            starts = time_segments(np.r_[ctx, t], step)[len(ctx) :]
            step_in = t - np.r_[ctx[-1:] if len(ctx) else t[:1], t[:-1]]  # 0 for the log's first
            back = step_in <= 0
            back[0] &= bool(done)
            part.untrusted += int(back.sum())
            if step > 0:
                part.gaps += int(np.sum(step_in > GAP_FACTOR * step))
            if not done:
                starts[0] = False  # the log's first frame opens the first segment
            at = np.flatnonzero(starts) + done
            if len(at):
                if prev is None:
                    part.first_start = int(at[0])
                inside = np.diff(at if prev is None else np.r_[prev, at])
                part.short_inside += int(inside[inside < MIN_SEGMENT_FRAMES].sum())
                part.starts += len(at)
                prev = part.last_start = int(at[-1])
            ctx = np.r_[ctx, t][-2:]
            done += len(t)
        inv = {v: k for k, v in names.items()}
        part.pairs = {(inv[li], inv[ki]): m for (li, ki), m in counts.items()}
        return part

    pairs: dict[tuple[str, str], int] = {}
    segments = untrusted = gaps = short = 0
    seg_start = 0  # first row of the open segment
    for part in _map_ranges(pf, src, threads, one):
        for k, m in part.pairs.items():
            pairs[k] = max(pairs.get(k, 0), m)
        untrusted += part.untrusted
        gaps += part.gaps
        if part.starts:  # the segment open before the range closes at its first start
            closed = part.first_start - seg_start
            short += closed if closed < MIN_SEGMENT_FRAMES else 0
            segments += part.starts
            short += part.short_inside
            seg_start = part.last_start
    if rows:
        final = rows - seg_start
        segments += 1
        short += final if final < MIN_SEGMENT_FRAMES else 0
    return LogScan(rows, pairs, step, max(segments, 1), untrusted, gaps, short)


# ---------------------------------------------------------------------- per-frame issues
class FrameIssues:
    """Per-frame problems found while decoding: status bits and detail texts, in order.

    Args:
        n: frames of the chunk.
    """

    def __init__(self, n: int) -> None:
        self.code = np.zeros(n, np.int64)
        self.items: list[tuple[np.ndarray, str]] = []

    def add(self, rows: np.ndarray, bit: int, detail: str) -> None:
        """Set ``bit`` (0: none, a detail of an estimator bit) and ``detail`` on ``rows``."""
        if rows.any():
            self.code[rows] |= bit
            self.items.append((rows, detail))

    def details(self) -> Any:
        """``(n,)`` pyarrow string array: each frame's details joined by ``"; "`` (null: none).

        Vectorised: the frames are grouped by which details they have (few combinations).
        """
        import pyarrow as pa

        n = len(self.code)
        if not self.items:
            return pa.nulls(n, pa.string())
        has = np.stack([rows for rows, _ in self.items], 1)  # (n, items)
        packed = np.packbits(has, axis=1)
        combos, which = np.unique(packed, axis=0, return_inverse=True)
        bits = np.unpackbits(combos, axis=1)[:, : len(self.items)].astype(bool)
        texts = ["; ".join(t for (_, t), b in zip(self.items, row, strict=True) if b) or None
                 for row in bits]  # fmt: skip
        return string_array(texts).take(numpy_to_arrow(which.reshape(-1)))


def status_text(code: np.ndarray) -> Any:
    """``(n,)`` pyarrow string array of :func:`~torchcontact.status_messages` per code."""
    code = np.asarray(code, np.int64).reshape(-1)
    if len(code) and 0 <= code.min() and code.max() < 1 << 16:  # status bits: count, not sort
        uniq = np.flatnonzero(np.bincount(code))
        lut = np.zeros(int(uniq[-1]) + 1, np.int64)
        lut[uniq] = np.arange(len(uniq))
        which = lut[code]
    else:
        uniq, which = np.unique(code, return_inverse=True)
    texts = string_array([status_messages(int(c)) for c in uniq])
    return texts.take(numpy_to_arrow(which.reshape(-1)))


# ---------------------------------------------------------------------- one chunk
@dataclass
class Decoded:
    """One chunk as arrays: inputs in the model's joint order, contacts in the log's slots.

    Attributes:
        n: frames.
        t_ns: the chunk's ``t_ns`` as a pyarrow int64 array, ns.
        t: ``(n,)`` int64 stamps, ns.
        q: ``(n, nv)`` positions, model order (NaN where malformed).
        qd: ``(n, nv)`` velocities (logged, or derived by :meth:`ChunkDecoder.derive`).
        qdd: ``(n, nv)`` accelerations likewise.
        ft: sensor -> ``(n, 6)`` readings.
        tau: ``(n, nv)`` measured torques or None.
        base: ``{omega, domega, proper_acc}`` ``(n, 3)`` each, or empty.
        extra: residual feature columns, ``(n,)`` float64 each.
        records: the chunk's contact records (every record, in order).
        fields: the contact struct's child arrays by name (carried to the output).
        slot: ``(M,)`` each record's slot in ``contacts`` (-1: not estimated).
        contacts: the slots (tensors on the model's device and dtype), or None before
            :meth:`ChunkDecoder.slots`.
        issues: the frames' problems found so far.
        starts: ``(n,)`` bool, a frame starts a time segment (None: not computed).
        short: ``(n,)`` bool, the frame cannot be differentiated (derived ``qd``/``qdd`` only).
        row: the chunk's first row in the log.
        ft_cov: sensor -> ``(n, 6, 6)`` reading noise covariances of the log's ``ft_cov.<s>``
            column (:attr:`ChunkDecoder.cov_sensors`; identity on frames whose value is
            malformed, which get status bit 1).
        located: the chunk's localization, when the reader computed it
            (:meth:`~torchcontact.logs.chunks.LogEstimator.localized`), else None.
    """

    n: int
    t_ns: Any
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray | None
    qdd: np.ndarray | None
    ft: dict[str, np.ndarray]
    tau: np.ndarray | None
    base: dict[str, np.ndarray]
    extra: dict[str, np.ndarray]
    records: ContactRecords
    fields: dict[str, Any]
    slot: np.ndarray
    contacts: Contacts | None
    issues: FrameIssues
    starts: np.ndarray | None = None
    short: np.ndarray | None = None
    row: int = 0
    ft_cov: dict[str, np.ndarray] = field(default_factory=dict)
    located: Any = None


class ChunkDecoder:
    """Arrow chunks of one log -> :class:`Decoded` (numpy; no per-frame Python).

    Args:
        model: the robot.
        perm: the log's joint columns -> the model's order.
        width: joints of the log (``len(perm)`` unless the log has joints the robot lacks).
        sensors: sensors in use.
        contact_fields: fields of the contact struct (empty: no contacts column).
        derived: columns derived from ``q`` (not read).
        region: per body, its sensor region (-1: outside every sensor's subtree).
        layout: the log's slot layout (None: one covering each chunk's records).
        friction: default friction coefficient of the cone records (None: none).
        cones: check the friction-cone fields (``--constraints``).
        extra_columns: residual feature columns.
        source: file name for messages.
    """

    def __init__(
        self,
        model: RobotModel,
        perm: np.ndarray,
        width: int,
        sensors: Sequence[str],
        contact_fields: Sequence[tuple[str, Any]],
        derived: Sequence[str],
        region: Sequence[int],
        layout: SlotLayout | None = None,
        friction: float | None = None,
        cones: bool = False,
        extra_columns: Sequence[str] = (),
        source: str = "",
    ) -> None:
        self.model = model
        self.perm = perm
        self.width = width
        self.sensors = list(sensors)
        self.contact_fields = list(contact_fields)
        self.derived = list(derived)
        self.region = region
        self.layout = layout
        #: the log's layout is being scanned (:func:`~torchcontact.logs.pipeline.open_prepared`):
        #: chunks are decoded without slots until it is set
        self.layout_pending = False
        self.friction = friction
        self.cones = cones
        self.extra_columns = list(extra_columns)
        self.source = source
        self._link_ok: dict[str | None, str | None] = {}
        #: the log is one time segment (a short one is the whole log)
        self.whole_log_segment = False
        #: sensors whose per-frame ``ft_cov.<s>`` column weighs the solve (read by decode)
        self.cov_sensors: list[str] = []

    # ------------------------------------------------------------------ links
    def link_problem(self, link: str | None) -> str | None:
        """Why contacts on ``link`` cannot be estimated (None: they can)."""
        if link not in self._link_ok:
            model = self.model
            if link is None:
                msg: str | None = "contact without a link"
            elif link not in model.frames:
                msg = f"unknown link {link!r}"
            elif self.region[model.frame(link).body] < 0:
                msg = f"link {link!r} is outside every F/T sensor's subtree"
            else:
                msg = None
            self._link_ok[link] = msg
        return self._link_ok[link]

    def usable(self, link: str, kind: str) -> bool:
        """Whether a ``(link, kind)`` pair can hold an estimated contact."""
        return kind in KINDS and self.link_problem(link) is None

    # ------------------------------------------------------------------ a chunk
    def _vectors(self, table: Any, name: str, n: int, bit: int, issues: FrameIssues) -> np.ndarray:
        vals, bad = vectors(table.column(name), n)
        issues.add(bad, bit, f"{name} is not {n} floats")
        return vals

    def decode(self, table: Any, first_row: int = 0) -> Decoded:
        """The arrays of a chunk (derived ``qd``/``qdd`` are None until :meth:`derive`).

        Args:
            table: pyarrow table or record batch in the log format.
            first_row: the chunk's first row in the log (for messages).

        Raises:
            LogError: some but not all base-motion columns, a bad ``t_ns``, a contact
                cone field of a non-numeric type.
        """
        import pyarrow as pa

        if isinstance(table, pa.RecordBatch):
            table = pa.Table.from_batches([table])
        N, nv, perm = table.num_rows, self.width, self.perm  # nv: the log's joints
        issues = FrameIssues(N)
        t_col = table.column("t_ns")
        t = timestamps(t_col, self.source, first_row)
        q = _joints(self._vectors(table, "q", nv, 2, issues), perm)
        qd = qdd = None
        if "qd" not in self.derived:
            qd = _joints(self._vectors(table, "qd", nv, 2, issues), perm)
        if "qdd" not in self.derived:
            qdd = _joints(self._vectors(table, "qdd", nv, 2, issues), perm)
        ft = {s: self._vectors(table, ft_column(s), 6, 1, issues) for s in self.sensors}
        tau = None
        if "tau_measured" in table.column_names:
            tau = _joints(self._vectors(table, "tau_measured", nv, 16, issues), perm)
        base = {}
        for col, key in BASE_COLUMNS.items():
            if col in table.column_names:
                base[key] = self._vectors(table, col, 3, 2, issues)
        if base and len(base) != 3:
            raise LogError(f"{self.source}: need all of {list(BASE_COLUMNS)} or none")
        extra = {
            c: np.array(arrow_to_numpy(table.column(c), np.float64)) for c in self.extra_columns
        }
        if self.contact_fields:
            records, fields, malformed = read_contacts(table.column("contacts"), self.cones)
            bad_record = self._check_contacts(records, malformed, N, issues)
        else:
            records, fields, bad_record = ContactRecords.empty(), {}, np.zeros(0, bool)
        slot = np.full(len(records), -1, np.int64)
        slot[~bad_record] = 0  # placed by slots()
        ft_cov = {s: self._covariances(table, s, issues, first_row) for s in self.cov_sensors}
        t_arrow = numpy_to_arrow(t, pa.int64())
        return Decoded(N, t_arrow, t, q, qd, qdd, ft, tau, base, extra, records,
                       fields, slot, None, issues, row=first_row, ft_cov=ft_cov)  # fmt: skip

    def _covariances(
        self, table: Any, sensor: str, issues: FrameIssues, first_row: int
    ) -> np.ndarray:
        """``(n, 6, 6)`` of a sensor's ``ft_cov`` column, each checked symmetric positive definite.

        Raises:
            InputError: a finite covariance that is not symmetric positive definite (names the
                file, the row and the smallest eigenvalue).
        """
        name = ft_cov_column(sensor)
        vals, malformed = vectors(table.column(name), 36)
        issues.add(malformed, 1, f"{name} is not 36 floats")
        vals = vals.reshape(-1, 6, 6)
        bad = ~np.isfinite(vals).all((1, 2))
        issues.add(bad & ~malformed, 1, f"{name} is not finite")
        if bad.any():  # Arrow's memory is read-only
            vals = vals.copy()
            vals[bad] = np.eye(6)
        scale = np.abs(vals).max((1, 2))
        asym = np.abs(vals - vals.transpose(0, 2, 1)).max((1, 2)) > 1e-9 * scale
        lam = np.linalg.eigvalsh(0.5 * (vals + vals.transpose(0, 2, 1))).min(1)
        wrong = asym | ~(lam > 1e-12 * scale)
        if wrong.any():
            i = int(np.flatnonzero(wrong)[0])
            what = (
                "not symmetric"
                if asym[i]
                else f"not positive definite (smallest eigenvalue {lam[i]:.3g})"
            )
            raise InputError(
                f"{self.source}: {name} of row {first_row + i} is {what}; a covariance must be"
                " symmetric positive definite"
            )
        return vals

    def slots(self, d: Decoded, dtype: Any, device: Any) -> None:
        """Place the good records of ``d`` in the log's slots (``d.contacts``, ``d.slot``)."""
        if self.layout_pending:  # a chunk would get a layout of its own (another program)
            raise RuntimeError("ChunkDecoder.slots before the log's slot layout is set")
        good = np.flatnonzero(d.slot >= 0)
        layout = self.layout
        # every record good (the common case): no copy of the records
        sub = d.records if len(good) == len(d.records) else d.records.select(good)
        slot = None
        if layout is not None and len(good):
            slot = layout.assign(sub)  # computed once: from_records takes it
            if (slot < 0).any():
                # a pair beyond the log's layout (the scan saw other data): this chunk gets its
                # own
                layout, slot = None, None
        contacts, slot_good = Contacts.from_records(
            sub, d.n, layout, dtype=dtype, device=device, friction=self.friction, slot=slot
        )
        d.slot[good] = slot_good
        d.contacts = contacts

    def derive(
        self, d: Decoded, qd: np.ndarray, qdd: np.ndarray, starts: np.ndarray, length: np.ndarray
    ) -> None:
        """Set the segment starts and the derived ``qd``/``qdd`` of a chunk.

        Frames whose time segment has fewer than ``MIN_SEGMENT_FRAMES`` frames (``length``, from
        :meth:`~torchcontact.logs.derive.DerivativeStream.derive`; 0 for the first frames of a
        segment that the causal filter cannot fit) get status :data:`NOT_DIFFERENTIABLE` and a
        detail saying so; their derivatives stay NaN.
        """
        d.starts = starts
        if not self.derived:
            return
        if "qd" in self.derived:
            d.qd = qd
        if "qdd" in self.derived:
            d.qdd = qdd
        d.short = length < MIN_SEGMENT_FRAMES
        where = "the log" if self.whole_log_segment else "its t_ns segment"
        for k in range(1, MIN_SEGMENT_FRAMES):
            d.issues.add(
                d.short & (length == k), NOT_DIFFERENTIABLE,
                f"too few frames to derive qd/qdd: {where} has {k} frame{'s' * (k > 1)}"
                + ("" if self.whole_log_segment else
                   f" (t_ns is cut at repeated or backward stamps and at gaps over"
                   f" {GAP_FACTOR:g} x the median step)"),
            )  # fmt: skip
        # the causal differentiator (length 0: fewer frames before it than its coefficients)
        d.issues.add(
            d.short & (length == 0), NOT_DIFFERENTIABLE,
            "too few frames before it to derive qd/qdd causally (the first frames of"
            f" {where}, up to the causal filter's polynomial order)",
        )  # fmt: skip

    # ------------------------------------------------------------------ record checks
    def _check_contacts(
        self,
        records: ContactRecords,
        malformed: dict[str, np.ndarray],
        n: int,
        issues: FrameIssues,
    ) -> np.ndarray:
        """Per-record problems -> frame issues (bit 128 or 4); returns the bad-record mask."""
        M = len(records)
        bit = np.zeros(M, np.int64)
        # per distinct link and kind (few), mapped back to the records
        ln, lc, kn, kc = records.name_codes()
        link_msg = [self.link_problem(None if n is None else str(n)) for n in ln]
        kind_msg = [None if k in KINDS else f"unknown contact kind {k!r}" for k in kn]
        if not self.cones and self._all_good(link_msg, kind_msg, lc, kc, malformed, kn):
            return np.zeros(M, bool)  # the common chunk: no per-record reasons to build
        reason = np.array(link_msg, dtype=object)[lc]
        reason = np.where(np.equal(reason, None), np.array(kind_msg, dtype=object)[kc], reason)
        bit[~np.equal(reason, None)] = 128
        # a vector field is required only by the kind that uses it
        kinds = records.kinds
        for need, col, width, kind in (
            (np.ones(M, bool), "position", 3, None),
            (kinds == "force_dir", "direction", 3, "force_dir"),
            (kinds == "known", "wrench", 6, "known"),
        ):
            bad = need & malformed[col] & (reason == None)  # noqa: E711 - object array
            reason[bad] = (
                "contact position is not 3 floats"
                if kind is None
                else f"{kind} contact without a {width}-float {col}"
            )
            bit[bad] = 4
        if self.cones:
            self._check_cones(records, malformed, reason, bit)
        bad_record = reason != None  # noqa: E711
        for msg in dict.fromkeys(reason[bad_record]):
            rows = np.zeros(n, bool)
            sel = reason == msg
            rows[records.frame[sel]] = True
            issues.add(rows, int(bit[sel][0]), msg)
        return bad_record

    @staticmethod
    def _all_good(
        link_msg: list[str | None],
        kind_msg: list[str | None],
        lc: np.ndarray,
        kc: np.ndarray,
        malformed: dict[str, np.ndarray],
        kn: np.ndarray,
    ) -> bool:
        """No record has a problem that :meth:`_check_contacts` (without cones) would name."""
        # the names the records use (the distinct names may hold a None no record has)
        for msg, codes in ((link_msg, lc), (kind_msg, kc)):
            used = np.bincount(codes, minlength=len(msg)) > 0
            if any(m is not None for m, u in zip(msg, used, strict=True) if u):
                return False
        if malformed["position"].any():
            return False
        names = list(kn)
        for kind, col in (("force_dir", "direction"), ("known", "wrench")):
            if kind in names and malformed[col][kc == names.index(kind)].any():
                return False
        return True

    def _check_cones(
        self,
        records: ContactRecords,
        malformed: dict[str, np.ndarray],
        reason: np.ndarray,
        bit: np.ndarray,
    ) -> None:
        """The friction-cone fields of pushing force and wrench records (bits 4 and 8)."""
        M = len(records)
        kinds = records.kinds
        push = (kinds != "known") if records.pushing is None else np.where(
            np.isnan(records.pushing), kinds != "known", records.pushing > 0.5
        )  # fmt: skip
        cone = push & ((kinds == "force") | (kinds == "wrench")) & np.equal(reason, None)
        nrm = np.full((M, 3), np.nan) if records.normals is None else records.normals
        no_normal = malformed.get("normal", np.ones(M, bool)) | ~np.isfinite(nrm).all(-1)
        nan = np.full(M, np.nan)
        mu = nan if records.friction is None else records.friction
        angle = nan if records.cone_angle is None else records.cone_angle
        default = self.friction
        checks = (
            (no_normal, 4, "pushing contact without a finite 3-float normal (--constraints)"),
            (~no_normal & ~(np.abs(nrm) > 0).any(-1), 8, "zero-length contact normal"),
            (~np.isnan(mu) & ~np.isnan(angle), 4, "contact gives both friction and cone_angle"),
            (~np.isnan(mu) & ~((mu > 0) & (mu < np.inf)), 4,
             "contact friction is not a finite number > 0"),
            (~np.isnan(angle) & ~((angle > 0) & (angle < np.pi / 2)), 4,
             "contact cone_angle is not in (0, pi/2) rad"),
            (np.isnan(mu) & np.isnan(angle) & (default is None), 4,
             "contact without friction or cone_angle (give --friction or --cone-angle)"),
        )  # fmt: skip
        for mask, b, msg in checks:
            bad = cone & mask & np.equal(reason, None)
            reason[bad] = msg
            bit[bad] = b


def _joints(values: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """``(N, nv)`` log-order joint values -> model order, C-contiguous (what kernels read)."""
    if np.array_equal(perm, np.arange(len(perm))):
        return values
    # numpy's a[:, perm] would be Fortran-ordered; "clip" skips the bounds check (perm's
    # indices are the log's own joint columns, from joint_permutation): 20 % less
    return values.take(perm, axis=1, mode="clip")


def stamps_and_positions(
    table: Any, perm: np.ndarray, width: int, source: str = "", first_row: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """``t_ns (N,)`` int64 and ``q (N, nv)`` in the model's joint order of a table (context).

    ``width``: the log's joints (more than ``len(perm)`` when it has joints the robot lacks).
    """
    q, _ = vectors(table.column("q"), width)
    return timestamps(table.column("t_ns"), source, first_row), _joints(q, perm)
