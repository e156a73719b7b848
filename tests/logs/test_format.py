import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.logs import format as fmt
from torchcontact.logs.derive import savgol_derivatives


def test_vectors_fixed_plain_and_bad_rows():
    v, bad = fmt.vectors(pa.array([[1.0, 2.0, 3.0], [4.0, 5.0], None, [7.0, 8.0, 9.0]]), 3)
    assert bad.tolist() == [False, True, True, False]
    assert v[3].tolist() == [7.0, 8.0, 9.0] and np.isnan(v[1]).all()
    fixed = fmt.fixed_list(np.arange(6.0).reshape(2, 3))
    v, bad = fmt.vectors(fixed.slice(1), 3)  # offsets of a slice are honoured
    assert v.tolist() == [[3.0, 4.0, 5.0]] and not bad.any()


def test_vectors_shortcuts_equal_the_row_by_row_reading():
    """The no-copy paths (plain lists n long, sliced, all null) read what the rows say."""
    rows = [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]
    cases = {
        "plain": pa.array(rows),
        "slice": pa.array(rows).slice(1),
        "large": pa.array(rows, pa.large_list(pa.float64())),
        "ints": pa.array([[1, 2], [3, 4]]),
        "total n*N, rows not n": pa.array([[1.0], [2.0, 3.0, 4.0]]),
        "all null": pa.array([None, None], pa.list_(pa.float64())),
        "null value": pa.array([[1.0, None], [2.0, 3.0]]),
    }
    for name, col in cases.items():
        v, bad = fmt.vectors(col, 2)
        want = [r if r is not None and len(r) == 2 else [None, None] for r in col.to_pylist()]
        want = np.array([[np.nan if x is None else x for x in r] for r in want])
        np.testing.assert_array_equal(v, want, err_msg=name)
        assert bad.tolist() == [r is None or len(r) != 2 for r in col.to_pylist()], name


def test_input_schema_metadata_roundtrip(tmp_path):
    schema = fmt.input_schema(["a", "b"], ["s"], derivatives=False)
    pq.write_table(schema.empty_table(), tmp_path / "x.parquet")
    back = pq.read_schema(tmp_path / "x.parquet")
    assert fmt.joint_names_of(back) == ["a", "b"]
    assert json.loads(back.metadata[fmt.META_JOINT_NAMES]) == ["a", "b"]
    assert back.names == ["t_ns", "q", "ft.s", "contacts"]
    with pytest.raises(ValueError, match="torchcontact.joint_names"):
        fmt.joint_names_of(pa.schema([("q", pa.float64())]), "f.parquet")


def test_savgol_exact_on_quadratics_uneven_time():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.integers(8_000_000, 12_000_000, 40))  # jittered 100 Hz
    s = t * 1e-9
    q = np.stack([1 + 2 * s - 3 * s**2, np.full_like(s, 0.5)], -1)
    qd, qdd = savgol_derivatives(t, q, 4)
    np.testing.assert_allclose(qd[:, 0], 2 - 6 * s, atol=1e-7)
    np.testing.assert_allclose(qdd[:, 0], -6.0, atol=1e-5)
    np.testing.assert_allclose(qd[:, 1], 0.0, atol=1e-9)


def test_savgol_chunked_with_context_equals_whole():
    rng = np.random.default_rng(1)
    t = np.arange(100) * 10_000_000
    q = np.sin(np.arange(100)[:, None] * 0.1 + rng.uniform(size=3))
    whole = savgol_derivatives(t, q, 5)
    # rows 40..60 with 5 frames of context on each side
    part = savgol_derivatives(t[35:65], q[35:65], 5, 5, 25)
    np.testing.assert_array_equal(part[0], whole[0][40:60])
    np.testing.assert_array_equal(part[1], whole[1][40:60])


def _corrupt_middle(path, n=2000, seed=0):
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + n] = np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))


def test_written_files_have_page_checksums_that_reading_verifies(tmp_path):
    n = 40_000
    tab = pa.table({"t_ns": np.arange(n), "x": np.random.default_rng(0).normal(size=n)})
    path = fmt.write_table(tab, tmp_path / "a.parquet", row_group_size=10_000)
    assert not (tmp_path / "a.parquet.tmp").exists()
    chunks = list(fmt.iter_chunks(fmt.open_log(path), ["t_ns", "x"], 4096))
    assert sum(c.num_rows for c in chunks) == n and {c.num_rows for c in chunks[:-1]} == {4096}
    _corrupt_middle(path)
    got = []
    with pytest.raises(fmt.LogError, match=r"a.parquet: corrupted data in row group \d \(rows"):
        for c in fmt.iter_chunks(fmt.open_log(path), ["t_ns", "x"], 4096, path):
            got.append(c)
    assert 0 < sum(c.num_rows for c in got) < n  # the chunks before the damage were yielded
    # plain pyarrow without verification reads the damaged page of a file without checksums
    # as garbage or fails; with checksums, the damage is always detected
    with pytest.raises(fmt.LogError, match="corrupted data"):
        fmt.read_log_columns(path, ["t_ns", "x"])


def test_log_writer_leaves_no_file_on_error(tmp_path):
    path = tmp_path / "w.parquet"
    schema = fmt.ft_log_schema("s")
    with pytest.raises(RuntimeError), fmt.LogWriter(path, schema) as w:
        w.write(pa.table({"t_ns": [1], "ft.s": fmt.fixed_list(np.zeros((1, 6)))}))
        raise RuntimeError("crash")
    assert not path.exists() and not (tmp_path / "w.parquet.tmp").exists()


def test_read_log_columns_by_joint_name(tmp_path):
    q = np.arange(12.0).reshape(4, 3)
    tab = pa.table({"t_ns": np.arange(4), "q": fmt.fixed_list(q), "temperature": np.ones(4)})
    path = fmt.write_table(
        tab.replace_schema_metadata({fmt.META_JOINT_NAMES: json.dumps(["a", "b", "grip"])}),
        tmp_path / "l.parquet",
    )
    cols = fmt.read_log_columns(path, ["t_ns", "q", "temperature"], joint_names=["b", "a"])
    np.testing.assert_array_equal(cols["q"], q[:, [1, 0]])  # model order; the gripper left out
    assert cols["t_ns"].dtype == np.int64 and cols["temperature"].tolist() == [1.0] * 4
    with pytest.raises(fmt.LogError, match=r"joints \['elbow'\] are not in the log"):
        fmt.read_log_columns(path, ["q"], joint_names=["a", "elbow"])
    with pytest.raises(fmt.LogError, match=r"missing columns \['qd'\]"):
        fmt.read_log_columns(path, ["qd"])
    with pytest.raises(fmt.LogError, match="no such file"):
        fmt.read_log_columns(tmp_path / "none.parquet", ["q"])
    assert fmt.read_rows(path, 2, 3, ["t_ns"])["t_ns"].to_pylist() == [2]


def test_contacts_column_roundtrip():
    from torchcontact.contacts import ContactRecords

    rec = ContactRecords(
        frame=[0, 0, 2],
        links=["a", "b", "a"],
        kinds=["force", "force_dir", "known"],
        positions=np.arange(9.0).reshape(3, 3),
        directions=[[np.nan] * 3, [0, 0, 1], [np.nan] * 3],
        wrenches=[[np.nan] * 6, [np.nan] * 6, list(range(6))],
    )
    col = fmt.contacts_column(rec, 3, {"true_force": np.ones((3, 3))})
    rows = col.to_pylist()
    assert [len(r) for r in rows] == [2, 0, 1]
    assert rows[0][0]["direction"] is None and rows[0][1]["direction"] == [0, 0, 1]
    assert rows[2][0]["wrench"] == list(range(6)) and rows[2][0]["true_force"] == [1, 1, 1]
    back, fields, malformed = fmt.read_contacts(col)
    assert back.frame.tolist() == [0, 0, 2] and back.links.tolist() == ["a", "b", "a"]
    np.testing.assert_array_equal(back.positions, rec.positions)
    assert malformed["direction"].tolist() == [True, False, True]
    assert "true_force" in fields
    with pytest.raises(fmt.InputError, match="ordered by frame"):
        fmt.contacts_column(rec.select(np.array([2, 0, 1])), 3)


def test_check_outputs_refuses_inputs_and_folders_holding_them(tmp_path):
    log = tmp_path / "logs" / "a.parquet"
    log.parent.mkdir()
    log.write_bytes(b"x")
    fmt.check_outputs([tmp_path / "b.parquet"], [log, None])
    with pytest.raises(fmt.InputError, match="is the input"):
        fmt.check_outputs([tmp_path / "logs" / ".." / "logs" / "a.parquet"], [log])
    link = tmp_path / "link.parquet"
    link.symlink_to(log)
    with pytest.raises(fmt.InputError, match="is the input"):
        fmt.check_outputs([link], [log])
    with pytest.raises(fmt.InputError, match="contains the input"):
        fmt.check_outputs([tmp_path / "logs"], [log])
