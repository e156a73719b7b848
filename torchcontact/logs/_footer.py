"""Parquet footers joined without re-encoding the data: the row groups of several files, one file.

A Parquet file is ``PAR1``, its column chunks, the footer (a Thrift ``FileMetaData`` in the compact
protocol), the footer's length (4 bytes, little-endian) and ``PAR1``. :func:`split_file` cuts a
file that pyarrow wrote into its data and its footer; :func:`join_footers` makes the footer of the
file whose data are those parts one after the other: the row groups of every part, their byte
offsets shifted to where the part's data lie, their ordinals renumbered, the row count summed. The
data bytes are never decoded or encoded again, so a chunk encoded once can be appended to the
output (and found again after a crash) while the footer is written at the end. The footers are not
decoded either: a part's row groups are copied byte by byte but for the fields rewritten, and the
rest of its footer (its schema and key-value metadata, most of its bytes) is skipped.

Only :mod:`torchcontact.logs.format` uses this module (the log format's one owner). The Thrift
field numbers are those of the Parquet format's ``parquet.thrift``.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable

__all__ = [
    "MAGIC",
    "FooterJoin",
    "footer_bytes",
    "footer_rows",
    "join_footers",
    "split_file",
    "standalone",
]

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
        size, et, i = _list_head(buf, i)
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


def _list_head(buf: bytes, i: int) -> tuple[int, int, int]:
    """A list's or set's header at ``i``: its size, its elements' type, the index after it."""
    head = buf[i]
    i += 1
    size, et = head >> 4, head & 0x0F
    if size == 15:
        size, i = _varint(buf, i)
    return size, et, i


#: The integer types (varints: a run of bytes with the high bit set, then one without).
_INTS = frozenset((_I16, _I32, _I64))


def _skip(buf: bytes, i: int, typ: int) -> int:
    """The index after a value of type ``typ`` at ``i`` (as :func:`_read`, building nothing).

    Varints and binaries are passed over inline, in lists and structs too: a footer is mostly
    integers and short lists of them, and a call per value cost most of a footer's join (the
    writer thread joins every chunk's footer as it appends it).
    """
    if typ in _INTS:
        while buf[i] & 0x80:
            i += 1
        return i + 1
    if typ in (_I8, _TRUE, _FALSE):
        return i + 1
    if typ == _DOUBLE:
        return i + 8
    if typ == _BINARY:
        n, i = _varint(buf, i)
        return i + n
    if typ in (_LIST, _SET):
        size, et, i = _list_head(buf, i)
        if et in (_I8, _TRUE, _FALSE):
            return i + size
        if et == _DOUBLE:
            return i + 8 * size
        if et in _INTS:
            for _ in range(size):
                while buf[i] & 0x80:
                    i += 1
                i += 1
            return i
        for _ in range(size):
            i = _skip(buf, i, et)
        return i
    if typ == _STRUCT:
        while True:
            head = buf[i]
            i += 1
            ft = head & 0x0F
            if ft == _STOP:
                return i
            if not head >> 4:  # a field id of its own: a varint
                while buf[i] & 0x80:
                    i += 1
                i += 1
            if ft in _INTS:
                while buf[i] & 0x80:
                    i += 1
                i += 1
            elif ft not in (_TRUE, _FALSE):
                i = _skip(buf, i, ft)
    raise FooterError(f"Thrift type {typ} in a Parquet footer")


def _copy_shifted(buf: bytes, i: int, out: bytearray, delta: int, shift: dict[int, object]) -> int:
    """Copy the struct at ``buf[i]`` into ``out`` with some of its fields rewritten.

    ``shift`` maps a field id to ``True`` (an i64 offset: ``delta`` added unless it is 0, unset),
    to an int (the field's new i16/i32 value), to a dict (a struct: copied with that map) or to a
    tuple holding one dict (a list of such structs). Every other byte is copied as it is: the
    result is what re-encoding the shifted struct gives (field headers do not change).

    Returns:
        The index after the struct.
    """
    fid = 0
    kept = i  # the bytes from here on are copied as they are, up to the next rewritten field
    while True:
        head = buf[i]
        i += 1
        ft = head & 0x0F
        if ft == _STOP:
            out += buf[kept:i]
            return i
        if head >> 4:
            fid += head >> 4
        else:
            n, i = _varint(buf, i)
            fid = _unzig(n)
        how = shift.get(fid) if ft not in (_TRUE, _FALSE) else None
        if how is None:
            if ft in _INTS:
                while buf[i] & 0x80:
                    i += 1
                i += 1
            elif ft not in (_TRUE, _FALSE):
                i = _skip(buf, i, ft)
            continue
        out += buf[kept:i]
        if isinstance(how, dict) and ft == _STRUCT:
            i = _copy_shifted(buf, i, out, delta, how)
        elif isinstance(how, tuple) and ft == _LIST and buf[i] & 0x0F == _STRUCT:
            size, j = buf[i] >> 4, i + 1
            if size == 15:
                size, j = _varint(buf, j)
            out += buf[i:j]
            i = j
            for _ in range(size):
                i = _copy_shifted(buf, i, out, delta, how[0])
        elif ft in (_I16, _I32, _I64) and not isinstance(how, (dict, tuple)):
            v, i = _read(buf, i, ft)
            new = (v + delta if v else v) if how is True else how
            _put_varint(out, _zig(new))  # type: ignore[arg-type]
        else:
            raise FooterError(f"field {fid} of a Parquet footer has Thrift type {ft}")
        kept = i


#: The fields a part's row group has shifted when it is placed in the joined file.
_CMD_SHIFT: dict[int, object] = dict.fromkeys(_CMD_OFFSETS, True)
_CC_SHIFT: dict[int, object] = {
    _CC_FILE_OFFSET: True,
    _CC_OFFSET_INDEX: True,
    _CC_COLUMN_INDEX: True,
    _CC_META: _CMD_SHIFT,
}


def _row_group_at(buf: bytes, i: int, out: bytearray, delta: int, ordinal: int) -> int:
    """Copy the RowGroup at ``buf[i]`` shifted by ``delta`` bytes with ``ordinal``."""
    shift = {_RG_COLUMNS: (_CC_SHIFT,), _RG_FILE_OFFSET: True, _RG_ORDINAL: ordinal}
    return _copy_shifted(buf, i, out, delta, shift)


def _parse(footer: bytes) -> list:
    fields, end = _read(footer, 0, _STRUCT)
    if end != len(footer):
        raise FooterError("trailing bytes after the Parquet footer")
    return fields  # type: ignore[return-value]


def _get(fields: list, fid: int) -> object:
    for f, _, v in fields:
        if f == fid:
            return v
    raise FooterError(f"a Parquet footer without field {fid}")


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

    Its fields are walked up to the row count (field 3, after the version and the schema; the
    row groups that follow are not read: a Ray driver reads the count of every part, and parsing
    the whole footer took 26 ms a part on the 2-core machine, against its copy's 27 ms).

    Raises:
        FooterError: a footer this module cannot read, or one without a row count.
    """
    try:
        fid, ft, i = _field(footer, 0, 0)
        while ft != _STOP:
            if fid == _FMD_NUM_ROWS and ft == _I64:
                n, _ = _varint(footer, i)
                return _unzig(n)
            i = i if ft in (_TRUE, _FALSE) else _skip(footer, i, ft)
            fid, ft, i = _field(footer, i, fid)
    except IndexError:
        raise FooterError("a truncated Parquet footer") from None
    raise FooterError("a Parquet footer without its row count")


def _field(buf: bytes, i: int, fid: int) -> tuple[int, int, int]:
    """The field header at ``buf[i]`` after field ``fid``: ``(field id, type, value start)``.

    The type is ``_STOP`` at the end of a struct.
    """
    head = buf[i]
    i += 1
    ft = head & 0x0F
    if ft == _STOP:
        return fid, ft, i
    if head >> 4:
        return fid + (head >> 4), ft, i
    n, i = _varint(buf, i)
    return _unzig(n), ft, i


def join_footers(parts: Iterable[tuple[int, bytes]]) -> bytes:
    """The footer of a file whose data are the given parts one after the other.

    Args:
        parts: ``(start, footer)`` per part, in file order: ``start`` the byte at which the part's
            column chunks begin in the joined file, ``footer`` the footer :func:`split_file` cut
            from the part's own file (whose chunks began at byte 4).

    Returns:
        The joined footer (schema, key-value metadata and writer of the first part; every part's
        row groups, their offsets shifted and ordinals renumbered; the summed row count). The
        parts' row groups are copied byte by byte but for the fields rewritten, and the rest of
        their footers (schema, metadata: most of their bytes) is skipped.

    Raises:
        FooterError: no part, or a footer this module cannot read.
    """
    join = FooterJoin()
    for start, footer in parts:
        join.add(start, footer)
    return join.footer()


class FooterJoin:
    """:func:`join_footers` a part at a time.

    Each part's row groups are shifted when it is added (the writer thread adds each part as it
    appends it, during the run); :meth:`footer` assembles the footer at the end.
    """

    def __init__(self) -> None:
        self.first: bytes | None = None
        self.groups = bytearray()
        self.count = 0
        self.rows = 0
        #: the first footer's other fields: id -> its value's bytes (the parts of one run have the
        #: same schema and metadata: a later part's field is passed over by comparing bytes)
        self._same: dict[int, bytes] = {}

    def add(self, start: int, footer: bytes) -> None:
        """Add the part whose column chunks begin at byte ``start`` (see :func:`join_footers`).

        Raises:
            FooterError: a footer this module cannot read (nothing of it is added).
        """
        groups, count, rows = bytearray(), self.count, 0
        values: dict[int, bytes] = {}
        try:
            delta = start - 4
            seen = set()
            fid, ft, i = _field(footer, 0, 0)
            while ft != _STOP:
                if fid == _FMD_NUM_ROWS and ft == _I64:
                    n, i = _read(footer, i, ft)
                    rows += n  # type: ignore[operator]
                elif fid == _FMD_ROW_GROUPS and ft == _LIST and footer[i] & 0x0F == _STRUCT:
                    size, i = footer[i] >> 4, i + 1
                    if size == 15:
                        size, i = _varint(footer, i)
                    for _ in range(size):
                        i = _row_group_at(footer, i, groups, delta, count)
                        count += 1
                elif ft not in (_TRUE, _FALSE):
                    same = self._same.get(fid)
                    if same is not None and footer.startswith(same, i):
                        # the compact protocol is read byte after byte: a value whose bytes
                        # begin with another whole value's bytes is that value
                        i += len(same)
                    else:
                        i0, i = i, _skip(footer, i, ft)
                        if self.first is None:
                            values[fid] = bytes(footer[i0:i])
                seen.add(fid)
                fid, ft, i = _field(footer, i, fid)
        except IndexError:
            raise FooterError("a truncated Parquet footer") from None
        if i != len(footer):
            raise FooterError("trailing bytes after the Parquet footer")
        if not {_FMD_NUM_ROWS, _FMD_ROW_GROUPS} <= seen:
            raise FooterError("a Parquet footer without its row count or row groups")
        if self.first is None:
            self.first, self._same = footer, values
        self.groups += groups
        self.count, self.rows = count, self.rows + rows

    def footer(self) -> bytes:
        """The joined footer of the parts added so far.

        Raises:
            FooterError: no part added.
        """
        first = self.first
        if first is None:
            raise FooterError("no part to join")
        # the first part's footer with the row count and the row groups replaced
        out = bytearray()
        h0 = 0
        try:
            fid, ft, i = _field(first, 0, 0)
            while ft != _STOP:
                end = i if ft in (_TRUE, _FALSE) else _skip(first, i, ft)
                out += first[h0:i]
                if fid == _FMD_NUM_ROWS:
                    _put_varint(out, _zig(self.rows))
                elif fid == _FMD_ROW_GROUPS:
                    if self.count < 15:
                        out.append(self.count << 4 | _STRUCT)
                    else:
                        out.append(0xF0 | _STRUCT)
                        _put_varint(out, self.count)
                    out += self.groups
                else:
                    out += first[i:end]
                h0 = end
                fid, ft, i = _field(first, end, fid)
        except IndexError:
            raise FooterError("a truncated Parquet footer") from None
        out.append(_STOP)
        return bytes(out)
