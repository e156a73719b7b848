"""A Ray worker's Parquet parts appended to the output as they are (format.write_encoded_part,
read_encoded_part, PartsWriter): any cut of a log into parts and chunks reads back as the log, and
a run appending parts tallies as one encoding tables."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcontact.errors import LogError
from torchcontact.logs.format import (
    PartsWriter,
    encoded_part_table,
    fixed_list,
    read_encoded_part,
    write_encoded_part,
)


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


@settings(max_examples=20, deadline=None)
@given(n=st.integers(1, 300), cuts=st.lists(st.integers(1, 300), max_size=4),
       chunk=st.integers(16, 128), at_once=st.integers(1, 4))  # fmt: skip
def test_parts_appended_read_back_as_the_log(tmp_path_factory, n, cuts, chunk, at_once):
    """Parts appended one by one, or ``at_once`` at a time with their bytes written in parallel
    (``append_many``): the log, and the same bytes either way."""
    from concurrent.futures import ThreadPoolExecutor

    tmp = tmp_path_factory.mktemp("parts")
    tab = _table(n, seed=n)
    bounds = sorted({0, n, *(c for c in cuts if c < n)})
    parts = []
    for i, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
        unit = tab.slice(lo, hi - lo)
        tables = [unit.slice(j, chunk) for j in range(0, unit.num_rows, chunk)]
        part, data = read_encoded_part(
            write_encoded_part(tables, tmp / f"p{i}.parquet", tab.schema)
        )
        assert part.rows == hi - lo and len(data) > len(part.data)
        parts.append(part)
    w = PartsWriter(tmp / "one.parquet", tab.schema)
    for part in parts:
        w.append(part)
    w.close()
    w = PartsWriter(tmp / "many.parquet", tab.schema)
    with ThreadPoolExecutor(3) as pool:
        for i in range(0, len(parts), at_once):
            index = w.append_many(parts[i : i + at_once], pool)
            assert [p.rows for p in index] == [p.rows for p in parts[i : i + at_once]]
    w.close()
    assert (tmp / "many.parquet").read_bytes() == (tmp / "one.parquet").read_bytes()
    back = pq.read_table(tmp / "one.parquet", page_checksum_verification=True)
    assert back.equals(tab, check_metadata=True)


def test_refusals(tmp_path):
    tab = _table(50)
    with pytest.raises(Exception, match="at least one table"):
        write_encoded_part([], tmp_path / "none.parquet", tab.schema)
    assert not any(tmp_path.iterdir())  # nothing left, not even the temporary file
    bad = tmp_path / "bad.parquet"
    write_encoded_part([tab], bad, tab.schema)
    data = bytearray(bad.read_bytes())
    data[-8:-4] = b"\xff\xff\xff\x7f"  # footer length beyond the file
    bad.write_bytes(bytes(data))
    with pytest.raises(LogError, match="bad.parquet: unreadable part"):
        read_encoded_part(bad)
    bad.write_bytes(b"not parquet at all")
    with pytest.raises(LogError, match="bad.parquet: unreadable part"):
        read_encoded_part(bad)
    # a damaged page: its checksum names the file when the driver reads the part's columns
    write_encoded_part([tab], bad, tab.schema)
    data = bytearray(bad.read_bytes())
    col = pq.ParquetFile(bad).metadata.row_group(0).column(1)  # ft: 50 x 6 doubles
    data[col.data_page_offset + col.total_compressed_size - 8] ^= 0xFF  # its page's values
    bad.write_bytes(bytes(data))
    part, buffer = read_encoded_part(bad)  # the footer is intact
    with pytest.raises(LogError, match="bad.parquet: unreadable part"):
        encoded_part_table(buffer, bad)


def test_a_run_appending_parts_tallies_as_one_encoding_tables(tmp_path):
    """The Ray engine's path (workers' Parquet parts appended) against the local engine's (tables
    encoded by the run): same file and the same summary, bad frames and their texts too."""
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
    for ray in (False, True):
        out = tmp_path / f"o{int(ray)}.parquet"
        with Run(out, "log.parquet") as run:
            run.start({"engine": "x"}, units, resume=False)
            done = []
            for u, (lo, hi) in enumerate(units):
                unit = tab.slice(lo, hi - lo)
                if ray:
                    path = run.part(u).with_suffix(".parquet")
                    write_encoded_part([unit], path, tab.schema)
                    unit = None
                done.append(Done(u, hi - lo, unit))
            summaries.append(run.execute(iter(done[::-1]), tab.schema))
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]  # byte for byte
    assert pq.read_table(pa.BufferReader(outs[1])).equals(tab)
    skip = ("seconds", "frames_per_s", "output")
    a, b = ({k: v for k, v in s.items() if k not in skip} for s in summaries)
    assert a == b and b["bad_frames"] == 3 and b["bad_details"] == [["F/T not finite", 3]]
    assert b["outside_training"] == 2


def test_two_writers_of_one_part_never_mix(tmp_path):
    """A part written by two writers at once (a pool actor left running by a killed driver, and
    the resumed run's writer): each writes a temporary file of its own, the last rename wins, and
    the part reads back whole. A part whose run has ended (its folder removed) is an error, and
    no folder is made again."""
    from torchcontact.logs.format import LogWriter

    tab = _table(200)
    path = tmp_path / "part-00000002.parquet"
    a, b = (LogWriter(path, tab.schema, unique_tmp=True, create_dirs=False) for _ in range(2))
    for k in range(0, 200, 50):  # interleaved, as two processes would write
        a.write(tab.slice(k, 50))
        b.write(tab.slice(k, 50))
    assert len(list(tmp_path.glob("*.tmp"))) == 2
    a.close()
    b.close()
    assert not list(tmp_path.glob("*.tmp"))
    assert pq.read_table(path, page_checksum_verification=True).equals(tab)
    gone = tmp_path / "ended.partial" / "part-00000000.parquet"
    with pytest.raises(OSError):
        write_encoded_part([tab], gone, tab.schema)
    assert not gone.parent.exists()


def test_a_damaged_part_among_those_ready_at_once(tmp_path):
    """Ray parts ready together are appended at once: with a damaged one among them, those before
    it are recorded, the run stops naming it, and the rest wait in their files; once the part is
    written again, the resumed run gives the whole log, the same bytes as one writing it."""
    from torchcontact.logs.run import Done, Run

    n = 400
    tab = pa.table({"t_ns": np.arange(n, dtype=np.int64),
                    "status_code": np.zeros(n, np.int32)})  # fmt: skip
    units = [(k, k + 100) for k in range(0, n, 100)]
    out = tmp_path / "o.parquet"

    def part(run, u):
        lo, hi = units[u]
        return write_encoded_part([tab.slice(lo, hi - lo)], run.part(u).with_suffix(".parquet"),
                                  tab.schema)  # fmt: skip

    with pytest.raises(LogError, match="part-00000002.parquet: unreadable part of a run"):
        with Run(out, "log.parquet") as run:
            run.start({"engine": "x"}, units, resume=False)
            for u in range(4):
                part(run, u)
            damaged = run.part(2)
            damaged.write_bytes(damaged.read_bytes()[:-30])  # its footer cut
            run.execute(iter([Done(u, 100) for u in (3, 2, 1, 0)]), tab.schema)
    with Run(out, "log.parquet") as run:
        assert [p.name for p in sorted(run.partial.glob("part-*"))] == [
            "part-00000000.index", "part-00000001.index", "part-00000002.parquet",
            "part-00000003.parquet"]  # fmt: skip
        part(run, 2)  # written again (a worker's retry)
        run.start({"engine": "x"}, units, resume=True)
        s = run.execute(iter([]), tab.schema)  # every unit kept: two recorded, two waiting
    assert s["resumed_chunks"] == 4 and s["processed_now"] == 0 and s["frames"] == n
    whole = tmp_path / "whole.parquet"
    w = PartsWriter(whole, tab.schema)
    for lo, hi in units:
        w.append(read_encoded_part(write_encoded_part([tab.slice(lo, hi - lo)],
                                                      tmp_path / "p.parquet", tab.schema))[0])  # fmt: skip
    w.close()
    assert out.read_bytes() == whole.read_bytes()
