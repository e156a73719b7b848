import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import torchcontact as tc
from torchcontact.logs import LogError, estimate_file
from torchcontact.logs.format import META_DERIVED, META_URDF_SHA256, META_VERSION, fixed_list


def _contacts(path):
    return pq.read_table(path).column("contacts").to_pylist()


def test_roundtrip_single_contact_frames_recover_truth(model, sim_log, tmp_path):
    out = tmp_path / "out.parquet"
    s = estimate_file(sim_log, model, out, batch_size=128)
    assert s["frames"] == 600 and s["derived"] == []
    tab = pq.read_table(out)
    meta = tab.schema.metadata
    assert json.loads(meta[b"torchcontact.joint_names"]) == list(model.joint_names)
    assert meta[META_URDF_SHA256].decode() == model.urdf_sha256
    assert meta[META_VERSION].decode() == tc.__version__
    assert set(tab.column("status").to_pylist()) == {"ok"}
    rows = tab.column("contacts").to_pylist()
    rank, unk = tab.column("rank.base_ft").to_numpy(), tab.column("unknowns.base_ft").to_numpy()
    n_checked = 0
    for i, row in enumerate(rows):
        if len(row) == 1:  # one force contact: 3 unknowns, identifiable from a 6-axis sensor
            assert rank[i] == unk[i] == 3
            np.testing.assert_allclose(row[0]["force"], row[0]["true_force"], atol=1e-8)
            np.testing.assert_allclose(row[0]["moment"], 0.0, atol=1e-12)
            n_checked += 1
    assert n_checked > 50
    assert not (pq.read_table(sim_log).column("t_ns").to_numpy() - tab["t_ns"].to_numpy()).any()
    assert not out.with_name("out.parquet.partial").exists()


def test_joint_columns_reordered_by_name_and_plain_lists(model, sim_log, tmp_path):
    tab = pq.read_table(sim_log)
    names = list(model.joint_names)
    perm = np.random.default_rng(0).permutation(len(names))
    cols = {}
    for c in tab.column_names:
        if c in ("q", "qd", "qdd"):
            v = np.stack(tab.column(c).to_numpy(zero_copy_only=False))[:, perm]
            cols[c] = pa.array(v.tolist(), pa.list_(pa.float64()))  # plain lists
        else:
            cols[c] = tab.column(c)
    meta = {b"torchcontact.joint_names": json.dumps([names[i] for i in perm])}
    shuffled = tmp_path / "shuffled.parquet"
    pq.write_table(pa.table(cols).replace_schema_metadata(meta), shuffled)
    a = pq.read_table(estimate_file(sim_log, model, tmp_path / "a.parquet")["output"])
    b = pq.read_table(estimate_file(shuffled, model, tmp_path / "b.parquet")["output"])
    np.testing.assert_array_equal(
        np.stack(a["joint_torques"].to_numpy(zero_copy_only=False)),
        np.stack(b["joint_torques"].to_numpy(zero_copy_only=False)),
    )


@pytest.mark.parametrize("change,match", [("drop", "missing \\['wrist_roll'\\]"), ("add", "extra")])
def test_missing_or_extra_joints_are_clear_errors(model, sim_log, tmp_path, change, match):
    tab = pq.read_table(sim_log)
    names = list(model.joint_names)
    names = names[:-1] + ["not_a_joint"] if change == "drop" else names
    if change == "add":
        names = names[:-1] + ["extra_joint"]
        match = "extra \\['extra_joint'\\]"
    path = tmp_path / "bad.parquet"
    pq.write_table(
        tab.replace_schema_metadata({b"torchcontact.joint_names": json.dumps(names)}), path
    )
    assert model.joint_names[-1] == "wrist_roll"
    with pytest.raises(LogError, match=match):
        estimate_file(path, model, tmp_path / "o.parquet")


def test_not_parquet_names_the_file(model, tmp_path):
    bad = tmp_path / "notes.parquet"
    bad.write_text("hello, not parquet")
    with pytest.raises(LogError, match="notes.parquet: not a readable Parquet file"):
        estimate_file(bad, model, tmp_path / "o.parquet")
    trunc = tmp_path / "trunc.parquet"
    trunc.write_bytes(b"PAR1" + b"\0" * 100)
    with pytest.raises(LogError, match="trunc.parquet"):
        estimate_file(trunc, model, tmp_path / "o.parquet")


def test_bad_frames_get_a_status_and_the_rest_is_processed(model, sim_log, tmp_path):
    tab = pq.read_table(sim_log)
    ft = np.stack(tab["ft.base_ft"].to_numpy(zero_copy_only=False)).copy()
    ft[10, 2] = np.nan
    ft_rows = ft.tolist()
    ft_rows[20] = ft_rows[20][:5]  # wrong vector length
    contacts = tab["contacts"].to_pylist()
    frame = dict(
        link="forearm_skin",
        kind="force",
        position=[0, 0, 0],
        direction=None,
        wrench=None,
        true_force=None,
    )
    contacts[30] = [dict(frame, link="no_such_link")]
    contacts[40] = [dict(frame, link="base_link")]  # root side of the base sensor
    contacts[50] = [dict(frame, kind="force_dir")]  # no direction
    cols = {c: tab[c] for c in tab.column_names}
    cols["ft.base_ft"] = pa.array(ft_rows, pa.list_(pa.float64()))
    cols["contacts"] = pa.array(contacts, tab.schema.field("contacts").type)
    path = tmp_path / "bad_frames.parquet"
    pq.write_table(pa.table(cols).replace_schema_metadata(tab.schema.metadata), path)
    out = pq.read_table(estimate_file(path, model, tmp_path / "o.parquet", batch_size=64)["output"])
    status = out["status"].to_pylist()
    assert status[10] == "non-finite F/T reading"
    assert status[20] == "ft.base_ft is not 6 floats"
    assert status[30] == "unknown link 'no_such_link'"
    assert status[40] == "link 'base_link' is outside every F/T sensor's subtree"
    assert "direction" in status[50]
    bad = {10, 20, 30, 40, 50}
    assert all(s == "ok" for i, s in enumerate(status) if i not in bad)
    jt = np.stack(out["joint_torques"].to_numpy(zero_copy_only=False))
    assert np.isnan(jt[[10, 20, 30, 40, 50]]).all() and np.isfinite(jt[[11, 21, 31]]).all()
    assert np.isnan(out["contacts"][30].as_py()[0]["force"]).all()


def test_qd_qdd_derived_from_q_when_missing(model, sim_log, sim_log_q_only, tmp_path):
    a = estimate_file(sim_log_q_only, model, tmp_path / "a.parquet", batch_size=100)
    b = estimate_file(sim_log_q_only, model, tmp_path / "b.parquet", batch_size=37)
    assert a["derived"] == ["qd", "qdd"]
    ta, tb = pq.read_table(a["output"]), pq.read_table(b["output"])
    assert json.loads(ta.schema.metadata[META_DERIVED])["columns"] == ["qd", "qdd"]
    assert "Savitzky-Golay" in json.loads(ta.schema.metadata[META_DERIVED])["method"]
    # chunking does not change the result (overlap carried across chunk boundaries)
    ja = np.stack(ta["joint_torques"].to_numpy(zero_copy_only=False))
    jb = np.stack(tb["joint_torques"].to_numpy(zero_copy_only=False))
    np.testing.assert_allclose(ja, jb, rtol=0, atol=1e-12)
    exact = pq.read_table(estimate_file(sim_log, model, tmp_path / "c.parquet")["output"])
    je = np.stack(exact["joint_torques"].to_numpy(zero_copy_only=False))
    # smoothing error of an 11-frame quadratic fit on the multi-sine trajectory: well under 1 %
    assert np.abs(ja - je).max() < 0.01 * np.abs(je).max()
    assert not np.allclose(ja, je, rtol=0, atol=1e-12)


def test_no_contacts_column(model, sim_log, tmp_path):
    tab = pq.read_table(sim_log).drop_columns(["contacts"])
    path = tmp_path / "nc.parquet"
    pq.write_table(tab, path)
    out = pq.read_table(estimate_file(path, model, tmp_path / "o.parquet")["output"])
    assert out["contacts"].to_pylist()[0] == [] and out["status"][0].as_py() == "ok"


def test_fixed_list_helper_shape():
    assert fixed_list(np.zeros((4, 6))).type.list_size == 6
