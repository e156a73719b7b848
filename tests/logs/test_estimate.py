import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import torchcontact as tc
from torchcontact.errors import InputError
from torchcontact.logs import LogError, estimate_file
from torchcontact.logs.format import (
    META_DERIVED,
    META_URDF_SHA256,
    META_VERSION,
    fixed_list,
)
from torchcontact.logs.run import Run
from torchcontact.status import status_messages


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


def _with_joints(sim_log, model, path, names, extra_value=0.0):
    """The log with joint list ``names``: robot joints keep their columns, others are constant."""
    tab = pq.read_table(sim_log)
    idx = {n: i for i, n in enumerate(model.joint_names)}
    cols = {}
    for c in tab.column_names:
        if c in ("q", "qd", "qdd"):
            v = np.stack(tab.column(c).to_numpy(zero_copy_only=False))
            z = np.full(len(v), extra_value)
            cols[c] = fixed_list(np.stack([v[:, idx[n]] if n in idx else z for n in names], -1))
        else:
            cols[c] = tab.column(c)
    meta = dict(tab.schema.metadata)
    meta[b"torchcontact.joint_names"] = json.dumps(names).encode()
    pq.write_table(pa.table(cols).replace_schema_metadata(meta), path)
    return path


def test_extra_log_joints_are_left_out_with_one_warning(model, sim_log, tmp_path, capsys):
    """A gripper joint the robot lacks: estimate, plot and train leave it out with one warning
    line naming it (--strict-joints refuses it); the estimates are those of the arm-only log."""
    from torchcontact.cli import main

    names = list(model.joint_names)
    log = _with_joints(sim_log, model, tmp_path / "grip.parquet", [*names[:3], "gripper", *names[3:]],
                       extra_value=0.02)  # fmt: skip
    out = tmp_path / "o.parquet"
    assert main(["estimate", str(log), "--out", str(out), "--quiet", "--robot", "tcarm"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: ") and "['gripper']" in err[0], err
    assert "grip.parquet: leaving out joints ['gripper'], which tcarm does not have" in err[0]
    ref = pq.read_table(estimate_file(sim_log, model, tmp_path / "ref.parquet")["output"])
    got = pq.read_table(out)
    for c in ("joint_torques", "residual.base_ft"):
        np.testing.assert_array_equal(
            np.stack(got[c].to_numpy(zero_copy_only=False)),
            np.stack(ref[c].to_numpy(zero_copy_only=False)),
        )
    assert got["contacts"].to_pylist() == ref["contacts"].to_pylist()
    # the same log, refused with --strict-joints (nothing written)
    strict = tmp_path / "strict.parquet"
    args = ["estimate", str(log), "--out", str(strict), "--robot", "tcarm", "--strict-joints"]
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "extra ['gripper']" in err[0]
    assert not strict.exists()
    # plot: the input log's joints matched the same way (the posed robot of robot.png and
    # nullspace.png; drawing them takes seconds, the matching is what is tested here)
    from torchcontact.logs.plot import _posed

    with pytest.warns(UserWarning, match=r"leaving out joints \['gripper'\]"):
        q, _ = _posed(got, model, log, 5)
    ref_q = np.stack(pq.read_table(sim_log)["q"].to_numpy(zero_copy_only=False))[5]
    np.testing.assert_array_equal(q.numpy(), ref_q)
    png = tmp_path / "png"
    assert main(["plot", str(out), "--input", str(log), "--out", str(png), "--strict-joints"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "extra ['gripper']" in err[0] and not png.exists()
    # training reads logs through the same matching
    from training.data import load_parquet

    with pytest.warns(UserWarning, match=r"leaving out joints \['gripper'\]"):
        ds = load_parquet([str(log)], model, "base_ft", [])
    assert len(ds) == 600
    ckpt = tmp_path / "ckpt"
    train = ["train", "fit", "--log", str(log), "--robot", "tcarm", "--out", str(ckpt)]
    assert main([*train, "--strict-joints"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "extra ['gripper']" in err[0] and not ckpt.exists()


def test_a_robot_joint_missing_from_the_log_is_an_error_naming_it(model, sim_log, tmp_path):
    names = list(model.joint_names)
    assert names[-1] == "wrist_roll"
    log = _with_joints(sim_log, model, tmp_path / "short.parquet", [*names[:-1], "gripper"])
    with pytest.raises(
        LogError, match=r"the log lacks joints \['wrist_roll'\] extra \['gripper'\]"
    ):
        estimate_file(log, model, tmp_path / "o.parquet")
    from torchcontact.cli import main

    for strict in ([], ["--strict-joints"]):
        assert main(["estimate", str(log), "--out", str(tmp_path / "o.parquet"), *strict]) == 1
    dup = _with_joints(sim_log, model, tmp_path / "dup.parquet", [*names, names[0]])
    with pytest.raises(LogError, match="duplicate joint names"):
        estimate_file(dup, model, tmp_path / "o.parquet")


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
    code = out["status_code"].to_numpy()
    status, detail = out["status"].to_pylist(), out["status_detail"].to_pylist()
    # the text is the code's, as in Python and ONNX; the detail says what the pipeline found
    assert all(s == status_messages(int(c)) for s, c in zip(status, code, strict=True))
    assert code[10] == 1 and detail[10] is None  # NaN reading: the estimator's own bit
    assert code[20] == 1 and detail[20] == "ft.base_ft is not 6 floats"
    assert code[30] == 128 and detail[30] == "unknown link 'no_such_link'"
    assert (
        code[40] == 128 and detail[40] == "link 'base_link' is outside every F/T sensor's subtree"
    )
    assert code[50] == 4 and detail[50] == "force_dir contact without a 3-float direction"
    bad = [10, 20, 30, 40, 50]
    assert np.count_nonzero(code) == 5 and set(np.flatnonzero(code)) == set(bad)
    assert all(s == "ok" for i, s in enumerate(status) if i not in bad)
    jt = np.stack(out["joint_torques"].to_numpy(zero_copy_only=False))
    assert np.isnan(jt[bad]).all() and np.isfinite(jt[[11, 21, 31]]).all()
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


def test_no_contacts_column_warns_once(model, sim_log, tmp_path):
    tab = pq.read_table(sim_log).drop_columns(["contacts"])
    path = tmp_path / "nc.parquet"
    pq.write_table(tab, path)
    with pytest.warns(UserWarning, match="no 'contacts' column") as record:
        s = estimate_file(path, model, tmp_path / "o.parquet", batch_size=64)  # 10 chunks
    assert len([w for w in record if "contacts" in str(w.message)]) == 1
    out = pq.read_table(s["output"])
    assert out["contacts"].to_pylist()[0] == [] and out["status"][0].as_py() == "ok"


def test_fixed_list_helper_shape():
    assert fixed_list(np.zeros((4, 6))).type.list_size == 6


def _with_column(tab, name, rows, path):
    cols = {c: tab[c] for c in tab.column_names}
    cols[name] = pa.array(rows, tab.schema.field(name).type)
    pq.write_table(pa.table(cols).replace_schema_metadata(tab.schema.metadata), path)
    return path


def _outputs_finite(out):
    """Per row: every output (joint torques, residuals, contact forces, moments) finite."""
    jt = np.stack(out["joint_torques"].to_numpy(zero_copy_only=False))
    ok = np.isfinite(jt).all(1)
    for c in out.column_names:
        if c.startswith("residual."):
            ok &= np.isfinite(out[c].to_numpy(zero_copy_only=False))
    for i, row in enumerate(out["contacts"].to_pylist()):
        ok[i] &= all(np.isfinite(c["force"]).all() and np.isfinite(c["moment"]).all() for c in row)
    return ok


def test_overflow_and_implausible_inputs_get_a_status(model, sim_log, tmp_path):
    tab = pq.read_table(sim_log)
    qd = np.stack(tab["qd"].to_numpy(zero_copy_only=False))
    qd[7, 2] = 1e200  # finite, overflows in the dynamics
    qd[9, 0] = 6.0  # finite, beyond 2 x the URDF limit of 2.5 rad/s
    ft = np.stack(tab["ft.base_ft"].to_numpy(zero_copy_only=False))
    ft[12, 2] = 900.0  # beyond the range given below
    path = _with_column(tab, "qd", qd.tolist(), tmp_path / "a.parquet")
    path = _with_column(pq.read_table(path), "ft.base_ft", ft.tolist(), path)
    rng = {"base_ft": [500.0] * 3 + [50.0] * 3}
    out = pq.read_table(estimate_file(path, model, tmp_path / "o.parquet", ft_range=rng)["output"])
    code, detail = out["status_code"].to_numpy(), out["status_detail"].to_pylist()
    assert code[7] == 64 and code[9] == 64 and code[12] == 64
    assert "qd of 'shoulder_yaw' beyond 2 x its URDF velocity limit 2.5" in detail[9]
    assert "ft.base_ft beyond its range" in detail[12]
    assert set(np.flatnonzero(code)) == {7, 9, 12}
    # without the plausibility check the overflow itself is flagged: outputs NaN, bit 32
    out = pq.read_table(
        estimate_file(path, model, tmp_path / "p.parquet", velocity_margin=None)["output"]
    )
    code = out["status_code"].to_numpy()
    assert code[7] == 32 and out["status"][7].as_py() == status_messages(32)
    assert code[9] == 0 and set(np.flatnonzero(code)) == {7}
    # status 0 always means finite outputs
    ok = out["status_code"].to_numpy() == 0
    assert (_outputs_finite(out)[ok]).all() and not _outputs_finite(out)[7]


def test_corrupted_input_is_detected_and_the_chunks_before_are_kept(model, sim_log, tmp_path):
    from torchcontact.logs.format import write_table

    # written by torchcontact (page checksums), small row groups so the damage is mid-file
    path = write_table(pq.read_table(sim_log), tmp_path / "in.parquet", row_group_size=100)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 2000] = np.random.default_rng(1).integers(0, 256, 2000, np.uint8).tobytes()
    path.write_bytes(bytes(data))
    out = tmp_path / "o.parquet"
    with pytest.raises(LogError, match=r"in.parquet: corrupted data in row group \d") as e:
        estimate_file(path, model, out, batch_size=50)
    assert "chunks are kept in" in str(e.value) and "for --resume" in str(e.value)
    parts = sorted((tmp_path / "o.parquet.partial").glob("part-*.index"))
    assert parts and not out.exists()  # nothing complete-looking, the processed chunks kept
    run = Run(out, path)  # the recorded chunks read back from o.parquet.tmp
    assert all(run.read_part(k).num_rows == 50 for k in range(len(parts)))


def test_garbage_values_without_checksums_never_report_ok_with_nan(model, sim_log, tmp_path):
    """A file written by another tool (no page checksums): bytes of a value page overwritten
    with garbage decode silently; those frames must not read "ok" with non-finite outputs."""
    import struct

    path = tmp_path / "plain.parquet"
    pq.write_table(
        pq.read_table(sim_log), path, row_group_size=100, compression="none", use_dictionary=False
    )
    meta = pq.ParquetFile(path).metadata
    leaf = [meta.schema.column(i).path for i in range(meta.num_columns)].index(
        "ft.base_ft.list.element"
    )
    chunk = meta.row_group(3).column(leaf)  # rows 300-399
    end = chunk.data_page_offset + chunk.total_compressed_size
    data = bytearray(path.read_bytes())
    garbage = struct.pack("<d", 1e308) * 6 + struct.pack("<d", float("nan")) * 6  # 2 frames
    data[end - len(garbage) : end] = garbage  # the last two frames' readings of that page
    path.write_bytes(bytes(data))
    s = estimate_file(path, model, tmp_path / "o.parquet", batch_size=64)
    out = pq.read_table(s["output"])
    code = out["status_code"].to_numpy()
    assert code[398] & 32 and code[399] & 1  # overflow from finite garbage; NaN garbage
    ok = code == 0
    assert _outputs_finite(out)[ok].all() and not _outputs_finite(out)[[398, 399]].any()
    assert s["bad_now"] == int((~ok).sum()) >= 2


def test_output_that_is_the_input_is_refused(model, sim_log, tmp_path):
    before = sim_log.read_bytes()
    with pytest.raises(InputError, match="is the input"):
        estimate_file(sim_log, model, sim_log)
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "a.parquet").write_bytes(before)
    from torchcontact.logs import estimate_files

    with pytest.raises(InputError, match="is the input"):  # out/<name> would be the input
        estimate_files([folder / "a.parquet", sim_log], tcarm(), folder)
    assert sim_log.read_bytes() == before and (folder / "a.parquet").read_bytes() == before
    assert sorted(p.name for p in folder.iterdir()) == ["a.parquet"]


def test_bad_options_are_refused_before_anything_is_written(model, sim_log, tmp_path):
    out = tmp_path / "o.parquet"
    with pytest.raises(InputError, match="--batch-size must be an integer >= 1"):
        estimate_file(sim_log, model, out, batch_size=0)
    with pytest.raises(InputError, match="--velocity-margin must be > 0"):
        estimate_file(sim_log, model, out, velocity_margin=-1.0)
    with pytest.raises(InputError, match="--ft-range wrist: not a sensor in use"):
        estimate_file(sim_log, model, out, ft_range={"wrist": 10.0})
    assert list(tmp_path.iterdir()) == []  # no .partial that would block a rerun
    s = estimate_file(sim_log, model, out, batch_size=256)
    assert s["frames"] == 600 and s["ok_now"] == 600


def tcarm():
    return tc.robots.tcarm_path()


def test_status_text_per_code():
    """Each frame's status text is its code's messages, for status bits (counted) and any other
    int64 code (sorted)."""
    from torchcontact.logs.decode import status_text
    from torchcontact.status import status_messages

    rng = np.random.default_rng(0)
    for code in (np.zeros(5, np.int64), rng.choice([0, 2, 4, 64, 66, 128], 500),
                 np.zeros(0, np.int64), np.array([1 << 40, 0, 3, 1 << 40])):  # fmt: skip
        assert status_text(code).to_pylist() == [status_messages(int(c)) for c in code]
