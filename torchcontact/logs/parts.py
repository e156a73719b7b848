"""Parquet parts encoded in parallel, joined into one output file by copying their bytes.

A Parquet file is ``PAR1``, the row groups' column chunks, the footer (a Thrift-encoded
``FileMetaData``), its length and ``PAR1``. The footer holds each column chunk's absolute byte
offsets. The Ray engine's workers each write their unit as a Parquet *part* with the output's
schema and writer options (:func:`write_part`); the driver then appends every part's column
chunks to the output unchanged and writes one footer whose row groups are the parts' row groups
with their offsets shifted to where the bytes now lie (:class:`PartStitcher`). The data pages,
their page checksums and statistics are the parts' own, so the output's pages are those a single
writer would have written; only the footer is rebuilt. Encoding, the costly part of writing
Parquet (about 1.7 us per iCub frame), runs in the workers, and the driver copies bytes.

The footer is decoded and encoded with a small generic codec of Thrift's compact protocol
(:func:`decode_struct`, :func:`encode_struct`): every field is kept as read, and only the offset
fields below are changed. Parts with a page index or Bloom filters (absolute offsets elsewhere in
the file) are refused: :func:`write_part` writes neither.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from torchcontact.errors import LogError

__all__ = ["PartStitcher", "decode_struct", "encode_struct", "read_part_columns", "write_part"]

_MAGIC = b"PAR1"

# compact protocol types
_STOP, _TRUE, _FALSE, _BYTE, _I16, _I32, _I64, _DOUBLE, _BINARY, _LIST, _SET, _MAP, _STRUCT = range(
    13
)
_UUID = 13

# Field ids (parquet.thrift): FileMetaData, RowGroup, ColumnChunk, ColumnMetaData
_FMD_NUM_ROWS, _FMD_ROW_GROUPS = 3, 4
_RG_COLUMNS, _RG_FILE_OFFSET, _RG_ORDINAL = 1, 5, 7
_CC_FILE_OFFSET, _CC_META = 2, 3
_CC_PAGE_INDEX = (4, 5, 6, 7)  # offset/column index offsets and lengths
_CMD_OFFSETS = (9, 10, 11)  # data, index, dictionary page offsets
_CMD_BLOOM = (14, 15)


# ---------------------------------------------------------------------- Thrift compact codec
class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def byte(self) -> int:
        b = self.data[self.pos]
        self.pos += 1
        return b

    def varint(self) -> int:
        shift = result = 0
        while True:
            b = self.byte()
            result |= (b & 0x7F) << shift
            if not b & 0x80:
                return result
            shift += 7

    def zigzag(self) -> int:
        n = self.varint()
        return (n >> 1) ^ -(n & 1)

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ValueError("truncated")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out


def _read_value(r: _Reader, ctype: int) -> Any:
    if ctype in (_TRUE, _FALSE):  # an element of a container: one byte
        return r.byte()
    if ctype == _BYTE:
        return r.byte()
    if ctype in (_I16, _I32, _I64):
        return r.zigzag()
    if ctype == _DOUBLE:
        return r.take(8)
    if ctype == _BINARY:
        return r.take(r.varint())
    if ctype == _UUID:
        return r.take(16)
    if ctype in (_LIST, _SET):
        head = r.byte()
        n, etype = head >> 4, head & 0x0F
        if n == 15:
            n = r.varint()
        return (etype, [_read_value(r, etype) for _ in range(n)])
    if ctype == _MAP:
        n = r.varint()
        if n == 0:
            return (0, 0, [])
        kv = r.byte()
        kt, vt = kv >> 4, kv & 0x0F
        return (kt, vt, [(_read_value(r, kt), _read_value(r, vt)) for _ in range(n)])
    if ctype == _STRUCT:
        return _read_struct(r)
    raise ValueError(f"unknown compact type {ctype}")


def _read_struct(r: _Reader) -> list[list]:
    fields: list[list] = []
    last = 0
    while True:
        head = r.byte()
        ctype = head & 0x0F
        if ctype == _STOP:
            return fields
        delta = head >> 4
        fid = last + delta if delta else r.zigzag()
        last = fid
        value = ctype == _TRUE if ctype in (_TRUE, _FALSE) else _read_value(r, ctype)
        fields.append([fid, ctype, value])


def decode_struct(data: bytes) -> list[list]:
    """A Thrift compact-protocol struct as ``[field id, compact type, value]`` entries.

    Values: ints for the integer types, ``bytes`` for binary/double/uuid, a bool for a boolean
    field, ``(element type, [values])`` for a list or set, ``(key type, value type, [(k, v)])``
    for a map, a nested entry list for a struct. :func:`encode_struct` writes it back
    byte for byte.

    Raises:
        ValueError: bytes that are not a whole compact-protocol struct.
    """
    try:
        r = _Reader(data)
        out = _read_struct(r)
    except IndexError:
        raise ValueError("truncated") from None
    if r.pos != len(data):
        raise ValueError(f"{len(data) - r.pos} bytes after the struct")
    return out


def _varint(n: int, out: bytearray) -> None:
    while True:
        if n < 0x80:
            out.append(n)
            return
        out.append((n & 0x7F) | 0x80)
        n >>= 7


def _zigzag(n: int, out: bytearray) -> None:
    _varint(n << 1 if n >= 0 else ((-n) << 1) - 1, out)


def _write_value(ctype: int, v: Any, out: bytearray) -> None:
    if ctype in (_TRUE, _FALSE, _BYTE):
        out.append(v & 0xFF)
    elif ctype in (_I16, _I32, _I64):
        _zigzag(v, out)
    elif ctype in (_DOUBLE, _UUID):
        out += v
    elif ctype == _BINARY:
        _varint(len(v), out)
        out += v
    elif ctype in (_LIST, _SET):
        etype, items = v
        if len(items) < 15:
            out.append((len(items) << 4) | etype)
        else:
            out.append(0xF0 | etype)
            _varint(len(items), out)
        for item in items:
            _write_value(etype, item, out)
    elif ctype == _MAP:
        kt, vt, items = v
        _varint(len(items), out)
        if items:
            out.append((kt << 4) | vt)
            for k, val in items:
                _write_value(kt, k, out)
                _write_value(vt, val, out)
    elif ctype == _STRUCT:
        _write_struct(v, out)
    else:
        raise ValueError(f"unknown compact type {ctype}")


def _write_struct(fields: list[list], out: bytearray) -> None:
    last = 0
    for fid, ctype, value in fields:
        if ctype in (_TRUE, _FALSE):
            ctype = _TRUE if value else _FALSE
        delta = fid - last
        if 0 < delta <= 15:
            out.append((delta << 4) | ctype)
        else:
            out.append(ctype)
            _zigzag(fid, out)
        last = fid
        if ctype not in (_TRUE, _FALSE):
            _write_value(ctype, value, out)
    out.append(_STOP)


def encode_struct(fields: list[list]) -> bytes:
    """Thrift compact-protocol bytes of a struct in :func:`decode_struct`'s form."""
    out = bytearray()
    _write_struct(fields, out)
    return bytes(out)


def _field(fields: list[list], fid: int) -> list | None:
    return next((f for f in fields if f[0] == fid), None)


# ---------------------------------------------------------------------- parts
def write_part(tables: Iterable[Any], path: str | Path, schema: Any) -> Path:
    """Write tables as one Parquet part (temporary name, atomic rename).

    The output's schema and writer options, one row group per table, no page index.

    Args:
        tables: the unit's output tables (at least one), in row order.
        path: the part's final path.
        schema: the output schema (with its metadata): every part of a run has the same.

    Raises:
        InputError: no table.
    """
    from torchcontact.logs.format import LogWriter

    with LogWriter(path, schema) as w:
        n = 0
        for tab in tables:
            w.write(tab)
            n += 1
        if n == 0:
            from torchcontact.errors import InputError

            raise InputError(f"{path}: a part needs at least one table")
    return Path(path)


def read_part_columns(path: str | Path, columns: list[str]) -> Any:
    """Columns of a part (page checksums verified).

    Raises:
        LogError: an unreadable part.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path, columns=columns, page_checksum_verification=True)
    except (OSError, pa.ArrowException) as exc:
        raise LogError(f"{path}: unreadable part of an interrupted run ({exc})") from None


def _footer(path: Path) -> tuple[int, list[list]]:
    """``(body end, FileMetaData)`` of a Parquet file (body: bytes 4 .. body end)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(4)
        f.seek(max(size - 8, 0))
        tail = f.read(8)
        if size < 12 or head != _MAGIC or tail[4:] != _MAGIC:
            raise LogError(f"{path}: not a Parquet file (no PAR1 magic at both ends)")
        n = struct.unpack("<I", tail[:4])[0]
        end = size - 8 - n
        if end < 4:
            raise LogError(f"{path}: damaged Parquet footer (length {n} of a {size}-byte file)")
        f.seek(end)
        data = f.read(n)
    try:
        return end, decode_struct(data)
    except ValueError as exc:
        raise LogError(f"{path}: damaged Parquet footer ({exc})") from None


def _shift_row_group(rg: list[list], shift: int, ordinal: int, path: Path) -> None:
    for f in rg:
        if f[0] == _RG_FILE_OFFSET:
            f[2] += shift
        elif f[0] == _RG_ORDINAL:
            f[2] = ordinal
    for cc in _field(rg, _RG_COLUMNS)[2][1]:  # type: ignore[index]
        if any(f[0] in _CC_PAGE_INDEX for f in cc):
            raise LogError(f"{path}: a part with a page index cannot be joined")
        for f in cc:
            if f[0] == _CC_FILE_OFFSET and f[2] > 0:  # deprecated: writers leave 0 (unset)
                f[2] += shift
            elif f[0] == _CC_META:
                for g in f[2]:
                    if g[0] in _CMD_OFFSETS:
                        g[2] += shift
                    elif g[0] in _CMD_BLOOM:
                        raise LogError(f"{path}: a part with Bloom filters cannot be joined")


class PartStitcher:
    """One Parquet file from Parquet parts, appended in order (:func:`write_part`).

    Writes ``<path>.tmp`` and renames it on :meth:`close`, as :class:`LogWriter` does.

    Args:
        path: the final file.
        schema: the output schema: a file without parts gets it (no rows); every part must
            have been written with it (checked on the footer's key-value metadata).
    """

    def __init__(self, path: str | Path, schema: Any) -> None:
        self.path = Path(path)
        self.schema = schema
        self.rows = 0
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self._f: Any = None
        self._meta: list[list] | None = None
        self._groups: list[list] = []

    def append(self, part: str | Path) -> None:
        """Append a part's row groups (its bytes copied, its footer's offsets shifted)."""
        part = Path(part)
        end, meta = _footer(part)
        if self._meta is None:
            self._meta = meta
        elif [f for f in meta if f[0] != _FMD_NUM_ROWS and f[0] != _FMD_ROW_GROUPS] != [
            f for f in self._meta if f[0] != _FMD_NUM_ROWS and f[0] != _FMD_ROW_GROUPS
        ]:
            raise LogError(f"{part}: written with another schema or writer than the first part")
        if self._f is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self._tmp, "wb")  # noqa: SIM115 - closed by close()/abort()
            self._f.write(_MAGIC)
        shift = self._f.tell() - 4
        rgs = _field(meta, _FMD_ROW_GROUPS)
        for rg in rgs[2][1] if rgs is not None else []:
            _shift_row_group(rg, shift, len(self._groups), part)
            self._groups.append(rg)
        with open(part, "rb") as src:
            src.seek(4)
            left = end - 4
            while left > 0:  # plain copies (copy_file_range would need the same filesystem)
                buf = src.read(min(left, 8 << 20))
                if not buf:
                    raise LogError(f"{part}: shorter than its footer says")
                self._f.write(buf)
                left -= len(buf)
        rows = _field(meta, _FMD_NUM_ROWS)
        self.rows += rows[2] if rows is not None else 0

    def close(self) -> None:
        """Write the footer and rename the file to its final name."""
        if self._meta is None:  # no part: an empty file with the schema
            from torchcontact.logs.format import LogWriter

            LogWriter(self.path, self.schema).close()
            return
        meta = [list(f) for f in self._meta]
        for f in meta:
            if f[0] == _FMD_NUM_ROWS:
                f[2] = self.rows
            elif f[0] == _FMD_ROW_GROUPS:
                f[2] = (f[2][0], self._groups)
        footer = encode_struct(meta)
        self._f.write(footer)
        self._f.write(struct.pack("<I", len(footer)))
        self._f.write(_MAGIC)
        self._f.close()
        self._f = None
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        """Drop the temporary file; the final name is left untouched."""
        if self._f is not None:
            self._f.close()
            self._f = None
        self._tmp.unlink(missing_ok=True)
