"""Parquet parts joined by their footers (logs/_footer.py) give one writer's file, byte for byte."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.logs import _footer
from torchcontact.logs.format import WRITE_OPTIONS, PartsWriter, encode_part, fixed_list


def _table(n, seed):
    rng = np.random.default_rng(seed)
    return pa.table(
        {
            "t_ns": pa.array(np.arange(n, dtype=np.int64) + 1000 * seed),
            "v": fixed_list(rng.standard_normal((n, 3))),
            "s": pa.array([None if i % 3 else f"x{i}" for i in range(n)], pa.string()),
        }
    ).replace_schema_metadata({b"k": b"v"})


def _file(tables, path, row_group_size=None):
    with pq.ParquetWriter(path, tables[0].schema, write_statistics=["t_ns"], **WRITE_OPTIONS) as w:
        for t in tables:
            w.write_table(t, row_group_size=row_group_size)


def test_parts_joined_are_one_writers_file(tmp_path):
    tables = [_table(n, i) for i, n in enumerate((50, 1, 0, 37))]
    _file(tables, tmp_path / "one.parquet")
    w = PartsWriter(tmp_path / "parts.parquet", tables[0].schema)
    for t in tables:
        w.append(encode_part(t, t.schema))
    w.close()
    assert (tmp_path / "parts.parquet").read_bytes() == (tmp_path / "one.parquet").read_bytes()

    # parts of several row groups each: offsets shifted, ordinals renumbered
    _file(tables, tmp_path / "rg.parquet", row_group_size=16)
    data = bytearray(b"PAR1")
    footers = []
    for i, t in enumerate(tables):
        _file([t], tmp_path / f"p{i}.parquet", row_group_size=16)
        chunks, footer = _footer.split_file((tmp_path / f"p{i}.parquet").read_bytes())
        footers.append((len(data), footer))
        data += chunks
    data += _footer.footer_bytes(_footer.join_footers(footers))
    assert bytes(data) == (tmp_path / "rg.parquet").read_bytes()
    meta = pq.ParquetFile(pa.BufferReader(bytes(data))).metadata
    assert meta.num_row_groups == 4 + 1 + 1 + 3 and meta.num_rows == 88


def test_a_footer_it_cannot_read_is_refused():
    with pytest.raises(_footer.FooterError, match="not a whole Parquet file"):
        _footer.split_file(b"PAR1 not a file")
    with pytest.raises(_footer.FooterError):
        _footer.join_footers([])


def test_a_footers_row_count(tmp_path):
    """``footer_rows`` reads the count up to its field (before the row groups): pyarrow's count,
    for any number of row groups; a footer cut before it, or without it, is refused."""
    for n, rg in ((0, None), (1, None), (37, 16), (1000, 7)):
        _file([_table(n, 1)], tmp_path / "f.parquet", row_group_size=rg)
        _, footer = _footer.split_file((tmp_path / "f.parquet").read_bytes())
        assert (
            _footer.footer_rows(bytes(footer)) == pq.read_metadata(tmp_path / "f.parquet").num_rows
        )
    with pytest.raises(_footer.FooterError, match="truncated"):
        _footer.footer_rows(bytes(footer)[:40])  # within the schema
    with pytest.raises(_footer.FooterError, match="without its row count"):
        _footer.footer_rows(b"\x15\x02\x00")  # field 1 (i32 version), then the end


def test_more_than_15_parts_and_a_truncated_footer(tmp_path):
    # 15 or more row groups take the compact protocol's long list header
    tables = [_table(3, i) for i in range(20)]
    _file(tables, tmp_path / "one.parquet")
    w = PartsWriter(tmp_path / "parts.parquet", tables[0].schema)
    parts = [encode_part(t, t.schema) for t in tables]
    for p in parts:
        w.append(p)
    w.close()
    assert (tmp_path / "parts.parquet").read_bytes() == (tmp_path / "one.parquet").read_bytes()
    with pytest.raises(_footer.FooterError, match="truncated"):
        _footer.join_footers([(4, parts[0].footer), (100, parts[1].footer[:-40])])


def test_footer_joined_part_by_part_and_after_a_resume(tmp_path):
    """PartsWriter joins each part's footer as it appends it: the same file as one writer's, also
    when a resumed writer starts from recorded parts; a part it cannot read adds nothing."""
    tables = [_table(n, i) for i, n in enumerate((7, 30, 1, 12))]
    _file(tables, tmp_path / "one.parquet")
    parts = [encode_part(t, t.schema) for t in tables]
    w = PartsWriter(tmp_path / "parts.parquet", tables[0].schema)
    done = [w.append(p) for p in parts[:2]]
    w.abort(keep=True)  # interrupted: its first two parts recorded
    w = PartsWriter(tmp_path / "parts.parquet", tables[0].schema, done)
    for p in parts[2:]:
        w.append(p)
    w.close()
    assert (tmp_path / "parts.parquet").read_bytes() == (tmp_path / "one.parquet").read_bytes()

    join = _footer.FooterJoin()
    join.add(4, parts[0].footer)
    before = join.footer()
    with pytest.raises(_footer.FooterError, match="truncated"):
        join.add(100, parts[1].footer[:-40])
    assert join.footer() == before == _footer.join_footers([(4, parts[0].footer)])
    with pytest.raises(_footer.FooterError, match="no part"):
        _footer.FooterJoin().footer()
