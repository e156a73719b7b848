"""Parquet parts joined by their bytes (torchcontact.logs.parts): the footer codec round-trips,
a joined file reads back as the parts' rows with its page checksums, and its column chunks are
those one writer writes for the same row groups."""

import struct

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcontact.errors import LogError
from torchcontact.logs.format import LogWriter, fixed_list
from torchcontact.logs.parts import PartStitcher, decode_struct, encode_struct, write_part


def _table(n: int, seed: int = 0) -> pa.Table:
    rng = np.random.default_rng(seed)
    detail = pa.array([None if i % 7 else f"frame {i}" for i in range(n)], pa.string())
    lists = pa.array([list(range(i % 3)) for i in range(n)], pa.list_(pa.int32()))
    tab = pa.table({
        "t_ns": np.arange(n, dtype=np.int64) * 1000,
        "ft": fixed_list(rng.normal(size=(n, 6))),
        "flag": pa.array(rng.random(n) > 0.5),
        "status_detail": detail,
        "ids": lists,
    })  # fmt: skip
    tab = tab.replace_schema_metadata({"torchcontact": '{"x": 1}'})
    sink = pa.BufferOutputStream()  # the types as Parquet gives them back (list field names)
    pq.write_table(tab.slice(0, 0), sink)
    return tab.cast(pq.read_schema(pa.BufferReader(sink.getvalue())))


def _body(path) -> bytes:
    data = open(path, "rb").read()
    n = struct.unpack("<I", data[-8:-4])[0]
    return data[: len(data) - 8 - n]


def _footer(path) -> bytes:
    data = open(path, "rb").read()
    n = struct.unpack("<I", data[-8:-4])[0]
    return data[len(data) - 8 - n : -8]


@settings(max_examples=20, deadline=None)
@given(n=st.integers(0, 300), cuts=st.lists(st.integers(1, 300), max_size=4),
       chunk=st.integers(16, 128))  # fmt: skip
def test_joined_parts_read_back_as_one_file(tmp_path_factory, n, cuts, chunk):
    tmp = tmp_path_factory.mktemp("parts")
    tab = _table(n, seed=n)
    bounds = sorted({0, n, *(c for c in cuts if c < n)})
    st_ = PartStitcher(tmp / "out.parquet", tab.schema)
    for i, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
        part = tab.slice(lo, hi - lo)
        tables = [part.slice(j, chunk) for j in range(0, part.num_rows, chunk)]
        st_.append(write_part(tables, tmp / f"p{i}.parquet", tab.schema))
    st_.close()
    assert not (tmp / "out.parquet.tmp").exists()
    back = pq.read_table(tmp / "out.parquet", page_checksum_verification=True)
    assert back.equals(tab, check_metadata=True)
    meta = pq.ParquetFile(tmp / "out.parquet").metadata
    assert meta.num_rows == n
    # the footer codec writes back what it read, byte for byte
    foot = _footer(tmp / "out.parquet")
    assert encode_struct(decode_struct(foot)) == foot


def test_same_column_chunks_as_one_writer(tmp_path):
    tab = _table(1000)
    chunks = [tab.slice(j, 128) for j in range(0, 1000, 128)]
    with LogWriter(tmp_path / "one.parquet", tab.schema) as w:
        for c in chunks:
            w.write(c)
    st_ = PartStitcher(tmp_path / "joined.parquet", tab.schema)
    for i in range(0, len(chunks), 3):
        st_.append(write_part(chunks[i : i + 3], tmp_path / f"p{i}.parquet", tab.schema))
    st_.close()
    assert _body(tmp_path / "one.parquet") == _body(tmp_path / "joined.parquet")
    one = pq.ParquetFile(tmp_path / "one.parquet").metadata
    joined = pq.ParquetFile(tmp_path / "joined.parquet").metadata
    assert one.num_row_groups == joined.num_row_groups == 8
    for g in range(8):
        a, b = one.row_group(g).to_dict(), joined.row_group(g).to_dict()
        assert a == b, g  # offsets, sizes, statistics


def test_no_part_gives_an_empty_file_with_the_schema(tmp_path):
    tab = _table(3)
    st_ = PartStitcher(tmp_path / "e.parquet", tab.schema)
    st_.close()
    assert pq.read_table(tmp_path / "e.parquet").schema.equals(tab.schema, check_metadata=True)


def test_refusals(tmp_path):
    tab = _table(50)
    # a damaged part: one clear error naming it, nothing published
    bad = tmp_path / "bad.parquet"
    write_part([tab], bad, tab.schema)
    data = bytearray(bad.read_bytes())
    data[-12:-8] = b"\xff\xff\xff\x7f"  # footer length beyond the file
    bad.write_bytes(bytes(data))
    st_ = PartStitcher(tmp_path / "o.parquet", tab.schema)
    with pytest.raises(LogError, match="bad.parquet: damaged Parquet footer"):
        st_.append(bad)
    bad.write_bytes(b"not parquet at all")
    with pytest.raises(LogError, match="bad.parquet: not a Parquet file"):
        st_.append(bad)
    st_.abort()
    assert not (tmp_path / "o.parquet").exists() and not (tmp_path / "o.parquet.tmp").exists()
    # a part of another schema, or with a page index (offsets outside the footer)
    st_ = PartStitcher(tmp_path / "o.parquet", tab.schema)
    st_.append(write_part([tab], tmp_path / "a.parquet", tab.schema))
    other = tab.drop_columns(["ids"])
    with pytest.raises(LogError, match="another schema"):
        st_.append(write_part([other], tmp_path / "b.parquet", other.schema))
    st_.abort()
    pq.write_table(tab, tmp_path / "idx.parquet", write_page_index=True)
    st_ = PartStitcher(tmp_path / "o.parquet", tab.schema)
    with pytest.raises(LogError, match="page index"):
        st_.append(tmp_path / "idx.parquet")
    st_.abort()


def test_a_run_joining_parts_tallies_as_one_writing_tables(tmp_path):
    """The Ray engine's path (workers' Parquet parts joined) against the local engine's (tables
    journalled and encoded): same rows and the same summary, bad frames and their texts too."""
    from torchcontact.logs.run import Done, Run

    n = 300
    code = np.zeros(n, np.int32)
    code[[5, 6, 250]] = 1  # bad frames, in two units
    code[[7, 100]] = 1024  # a warning bit: outputs kept, its detail counted
    status = pa.array(["ok" if c == 0 else "bad" if c == 1 else "ok" for c in code])
    detail = pa.array([None if c == 0 else "F/T not finite" if c == 1 else
                       "q[0] outside the training range" for c in code])  # fmt: skip
    tab = pa.table({"t_ns": np.arange(n, dtype=np.int64), "status_code": code,
                    "status": status, "status_detail": detail})  # fmt: skip
    units = [(0, 128), (128, 256), (256, 300)]
    summaries, outs = [], []
    for stitch in (False, True):
        out = tmp_path / f"o{int(stitch)}.parquet"
        with Run(out, "log.parquet") as run:
            run.start({"engine": "x"}, units, resume=False)
            done = []
            for u, (lo, hi) in enumerate(units):
                part = tab.slice(lo, hi - lo)
                if stitch:
                    write_part([part], run.part(u).with_suffix(".parquet"), tab.schema)
                    part = None
                done.append(Done(u, hi - lo, part))
            summaries.append(run.execute(iter(done[::-1]), tab.schema, stitch=stitch))
        outs.append(pq.read_table(out))
    assert outs[0].equals(outs[1], check_metadata=True) and outs[1].equals(tab)
    a, b = ({k: v for k, v in s.items() if k not in ("seconds", "frames_per_s", "output")}
            for s in summaries)  # fmt: skip
    assert a == b and b["bad_frames"] == 3 and b["bad_details"] == [["F/T not finite", 3]]
    assert b["outside_training"] == 2
