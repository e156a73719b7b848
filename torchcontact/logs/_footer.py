"""Parquet footers joined without re-encoding the data: the row groups of several files, one file.

A Parquet file is ``PAR1``, its column chunks, the footer (a Thrift ``FileMetaData`` in the compact
protocol), the footer's length (4 bytes, little-endian) and ``PAR1``. :func:`split_file` cuts a
file that pyarrow wrote into its data and its footer; :func:`join_footers` makes the footer of the
file whose data are those parts one after the other: the row groups of every part, their byte
offsets shifted to where the part's data lie, their ordinals renumbered, the row count summed. The
data bytes are never decoded or encoded again, so a chunk encoded once can be appended to the
output (and found again after a crash) while the footer is written at the end.

Only :mod:`torchcontact.logs.format` uses this module (the log format's one owner). The Thrift
field numbers are those of the Parquet format's ``parquet.thrift``.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable

__all__ = ["MAGIC", "footer_bytes", "footer_rows", "join_footers", "split_file", "standalone"]

MAGIC = b"PAR1"

# compact protocol types
_STOP, _TRUE, _FALSE, _I8, _I16, _I32, _I64, _DOUBLE, _BINARY = 0, 1, 2, 3, 4, 5, 6, 7, 8
_LIST, _SET, _MAP, _STRUCT = 9, 10, 11, 12

# parquet.thrift field ids: FileMetaData, RowGroup, ColumnChunk, ColumnMetaData
_FMD_NUM_ROWS, _FMD_ROW_GROUPS = 3, 4
_RG_COLUMNS, _RG_FILE_OFFSET, _RG_ORDINAL = 1, 5, 7
_CC_FILE_OFFSET, _CC_META, _CC_OFFSET_INDEX, _CC_COLUMN_INDEX = 2, 3, 4, 6
#: ColumnMetaData: data_page_offset, index_page_offset, dictionary_page_offset,
#: bloom_filter_offset (absolute byte offsets in the file)
_CMD_OFFSETS = (9, 10, 11, 14)


class FooterError(ValueError):
    """A footer this module cannot read (not a Parquet footer, or a Thrift type it lacks)."""


# ---------------------------------------------------------------------- compact protocol
def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = out = 0
    while True:
        b = buf[i]
        i += 1
        out |= (b & 0x7F) << shift
        if b < 0x80:
            return out, i
        shift += 7


def _unzig(n: int) -> int:
    return (n >> 1) ^ -(n & 1)


def _put_varint(out: bytearray, n: int) -> None:
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)


def _zig(n: int) -> int:
    return (n << 1) ^ (n >> 63)


# a value is: int (i8/i16/i32/i64), bool, bytes (binary or double's 8 raw bytes),
# list -> (elem_type, [values]), struct -> [(field_id, type, value)], map -> raw bytes kept
def _read(buf: bytes, i: int, typ: int) -> tuple[object, int]:
    if typ in (_I16, _I32, _I64):
        n, i = _varint(buf, i)
        return _unzig(n), i
    if typ == _I8:
        return buf[i], i + 1
    if typ in (_TRUE, _FALSE):  # a bool in a list: one byte
        return buf[i] == 1, i + 1
    if typ == _DOUBLE:
        return buf[i : i + 8], i + 8
    if typ == _BINARY:
        n, i = _varint(buf, i)
        return buf[i : i + n], i + n
    if typ in (_LIST, _SET):
        head = buf[i]
        i += 1
        size, et = head >> 4, head & 0x0F
        if size == 15:
            size, i = _varint(buf, i)
        items = []
        for _ in range(size):
            v, i = _read(buf, i, et)
            items.append(v)
        return (et, items), i
    if typ == _STRUCT:
        fields: list[tuple[int, int, object]] = []
        fid = 0
        while True:
            head = buf[i]
            i += 1
            ft = head & 0x0F
            if ft == _STOP:
                return fields, i
            delta = head >> 4
            if delta:
                fid += delta
            else:
                n, i = _varint(buf, i)
                fid = _unzig(n)
            if ft in (_TRUE, _FALSE):
                fields.append((fid, ft, ft == _TRUE))
            else:
                v, i = _read(buf, i, ft)
                fields.append((fid, ft, v))
    raise FooterError(f"Thrift type {typ} in a Parquet footer")


def _write(out: bytearray, typ: int, v: object) -> None:
    if typ in (_I16, _I32, _I64):
        _put_varint(out, _zig(v))  # type: ignore[arg-type]
    elif typ == _I8:
        out.append(v)  # type: ignore[arg-type]
    elif typ in (_TRUE, _FALSE):
        out.append(1 if v else 2)
    elif typ == _DOUBLE:
        out += v  # type: ignore[operator]
    elif typ == _BINARY:
        _put_varint(out, len(v))  # type: ignore[arg-type]
        out += v  # type: ignore[operator]
    elif typ in (_LIST, _SET):
        et, items = v  # type: ignore[misc]
        if len(items) < 15:
            out.append(len(items) << 4 | et)
        else:
            out.append(0xF0 | et)
            _put_varint(out, len(items))
        for x in items:
            _write(out, et, x)
    elif typ == _STRUCT:
        last = 0
        for fid, ft, x in v:  # type: ignore[attr-defined]
            t = (_TRUE if x else _FALSE) if ft in (_TRUE, _FALSE) else ft
            if 0 < fid - last <= 15:
                out.append((fid - last) << 4 | t)
            else:
                out.append(t)
                _put_varint(out, _zig(fid))
            if ft not in (_TRUE, _FALSE):
                _write(out, ft, x)
            last = fid
        out.append(_STOP)
    else:
        raise FooterError(f"Thrift type {typ} in a Parquet footer")


def _parse(footer: bytes) -> list:
    fields, end = _read(footer, 0, _STRUCT)
    if end != len(footer):
        raise FooterError("trailing bytes after the Parquet footer")
    return fields  # type: ignore[return-value]


def _encode(fields: list) -> bytes:
    out = bytearray()
    _write(out, _STRUCT, fields)
    return bytes(out)


def _get(fields: list, fid: int) -> object:
    for f, _, v in fields:
        if f == fid:
            return v
    raise FooterError(f"a Parquet footer without field {fid}")


def _shifted(fields: list, ids: Iterable[int], delta: int) -> list:
    # an offset of 0 is unset (data begin at byte 4): pyarrow writes the deprecated
    # ColumnChunk.file_offset as 0, and a file written at once keeps it so
    ids = set(ids)
    return [(f, t, v + delta if f in ids and v else v) for f, t, v in fields]


# ---------------------------------------------------------------------- files
def split_file(data: bytes) -> tuple[bytes, bytes]:
    """A whole Parquet file -> ``(its column chunks, its footer)``.

    The column chunks are the bytes between the leading ``PAR1`` and the footer; in the footer,
    their offsets count from the file's start (the first chunk at byte 4).

    Raises:
        FooterError: not a whole Parquet file.
    """
    if len(data) < 12 or data[:4] != MAGIC or data[-4:] != MAGIC:
        raise FooterError("not a whole Parquet file")
    n = struct.unpack("<I", data[-8:-4])[0]
    end = len(data) - 8 - n
    if end < 4:
        raise FooterError("a Parquet footer longer than its file")
    return data[4:end], data[end : len(data) - 8]


def standalone(chunks: bytes, footer: bytes) -> bytes:
    """The Parquet file of one part again (the inverse of :func:`split_file`)."""
    return MAGIC + chunks + footer + struct.pack("<I", len(footer)) + MAGIC


def footer_bytes(footer: bytes) -> bytes:
    """A footer as it ends a file: the footer, its length, ``PAR1``."""
    return footer + struct.pack("<I", len(footer)) + MAGIC


def footer_rows(footer: bytes) -> int:
    """The row count a footer records.

    Raises:
        FooterError: a footer this module cannot read.
    """
    try:
        return int(_get(_parse(footer), _FMD_NUM_ROWS))  # type: ignore[call-overload]
    except IndexError:
        raise FooterError("a truncated Parquet footer") from None


def join_footers(parts: Iterable[tuple[int, bytes]]) -> bytes:
    """The footer of a file whose data are the given parts one after the other.

    Args:
        parts: ``(start, footer)`` per part, in file order: ``start`` the byte at which the part's
            column chunks begin in the joined file, ``footer`` the footer :func:`split_file` cut
            from the part's own file (whose chunks began at byte 4).

    Returns:
        The joined footer (schema, key-value metadata and writer of the first part; every part's
        row groups; the summed row count).

    Raises:
        FooterError: no part, or a footer this module cannot read.
    """
    head: list | None = None
    groups: list = []
    rows = 0
    for start, footer in parts:
        fmd = _parse(footer)
        if head is None:
            head = fmd
        delta = start - 4
        rows += _get(fmd, _FMD_NUM_ROWS)  # type: ignore[operator]
        et, rgs = _get(fmd, _FMD_ROW_GROUPS)  # type: ignore[misc]
        for rg in rgs:
            cet, cols = _get(rg, _RG_COLUMNS)  # type: ignore[misc]
            new_cols = []
            for cc in cols:
                cc = _shifted(cc, (_CC_FILE_OFFSET, _CC_OFFSET_INDEX, _CC_COLUMN_INDEX), delta)
                cc = [
                    (f, t, _shifted(v, _CMD_OFFSETS, delta) if f == _CC_META else v)
                    for f, t, v in cc
                ]
                new_cols.append(cc)
            rg = [(f, t, (cet, new_cols) if f == _RG_COLUMNS else v) for f, t, v in rg]
            rg = _shifted(rg, (_RG_FILE_OFFSET,), delta)
            rg = [(f, t, len(groups) if f == _RG_ORDINAL else v) for f, t, v in rg]
            groups.append(rg)
    if head is None:
        raise FooterError("no part to join")
    out = []
    for f, t, v in head:
        if f == _FMD_NUM_ROWS:
            v = rows
        elif f == _FMD_ROW_GROUPS:
            v = (_STRUCT, groups)
        out.append((f, t, v))
    return _encode(out)
