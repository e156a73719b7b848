import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.simulation import simulate
from training.data import ResidualDataset, load_parquet, split_blocks


@pytest.mark.parametrize("lengths,block", [((1000,), 100), ((350, 17, 640), 64), ((5,), 2)])
def test_split_by_contiguous_blocks_leaks_no_frame(lengths, block):
    file_id = np.concatenate([np.full(n, i) for i, n in enumerate(lengths)])
    s = split_blocks(file_id, block, seed=1)
    parts = [s.train, s.val, s.test]
    allidx = np.concatenate(parts)
    assert len(allidx) == len(file_id) and len(np.unique(allidx)) == len(file_id)
    for a in range(3):
        for b in range(a + 1, 3):
            assert not np.intersect1d(parts[a], parts[b]).size
    for name, idx in zip(("train", "val", "test"), parts, strict=True):
        assert len(idx) > 0
        rebuilt = np.concatenate([np.arange(x, y) for x, y in s.blocks[name]])
        np.testing.assert_array_equal(rebuilt, idx)
        for x, y in s.blocks[name]:
            assert 0 < y - x <= block
            assert len(np.unique(file_id[x:y])) == 1  # a block never crosses files
    # blocks, not frames: far fewer runs than frames
    runs = np.count_nonzero(np.diff(s.test) != 1) + 1
    assert runs <= len(s.blocks["test"])


def test_split_is_seeded():
    f = np.zeros(500, int)
    a, b, c = split_blocks(f, 50, seed=0), split_blocks(f, 50, seed=0), split_blocks(f, 50, seed=1)
    np.testing.assert_array_equal(a.test, b.test)
    assert not np.array_equal(a.test, c.test)


def test_parquet_loader(tmp_path, arm):
    log = simulate(arm, 400, seed=2)
    nv = arm.nv
    contacts = []
    for i in range(400):
        row = [
            {"link": log.links[li], "position": list(log.contact_position[i, k])}
            for k, li in enumerate(log.contact_link[i])
            if li >= 0
        ]
        contacts.append(row)
    fsl = lambda a, n: pa.FixedSizeListArray.from_arrays(pa.array(a.reshape(-1)), n)  # noqa: E731
    table = pa.table(
        {
            "t_ns": pa.array(log.t_ns),
            "q": fsl(log.q, nv),
            "qd": fsl(log.qd, nv),
            "qdd": fsl(log.qdd, nv),
            "ft.base_ft": fsl(log.ft, 6),
            "contacts": pa.array(
                contacts,
                type=pa.list_(
                    pa.struct([("link", pa.string()), ("position", pa.list_(pa.float64(), 3))])
                ),
            ),
            "temperature": pa.array(log.temperature),
        }
    ).replace_schema_metadata({"torchcontact.joint_names": json.dumps(list(arm.joint_names))})
    p1, p2 = tmp_path / "a.parquet", tmp_path / "b.parquet"
    pq.write_table(table, p1)
    pq.write_table(table.slice(10, 20), p2)
    ds = load_parquet([p1, p2], "base_ft", extra=["temperature", "time"])
    ref = ResidualDataset.from_simulated(log, ["temperature", "time"])
    assert len(ds) == 420 and ds.joint_names == arm.joint_names
    np.testing.assert_array_equal(ds.q[:400], ref.q)
    np.testing.assert_array_equal(ds.ft[400:], ref.ft[10:30])
    np.testing.assert_array_equal(ds.contact_free[:400], ref.contact_free)
    assert ref.contact_free.any() and not ref.contact_free.all()
    np.testing.assert_array_equal(ds.file_id, np.r_[np.zeros(400), np.ones(20)])
    assert ds.extra["time"][400] == 0.0  # time since each file's start
    assert ds.feature_names()[-2:] == ["temperature", "time"]
    assert ds.features().shape == (420, 3 * nv + 2)
    with pytest.raises(ValueError, match="ft.nope"):
        load_parquet([p1], "nope")
    assert ds.sha256() != load_parquet([p1], "base_ft", extra=["temperature", "time"]).sha256()
