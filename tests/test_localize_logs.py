"""Localization in logs: simulated logs without skin, the per-chunk function, the output schema.

The chunk function (:func:`torchcontact.localize.localize_chunk`) gets what the log pipeline
decodes from a chunk (joint arrays, readings, skin records) and returns the records with the
localized ``force`` contacts added and the localization columns. Truth: a log simulated with
contacts on the panda's collision meshes (hand and fingers, wrist F/T sensor), without skin
(``simulate --no-skin``); noise-free, so the unambiguous frames give the true point and, once the
estimator has run on the filled-in records, the true force.
"""

from __future__ import annotations

import warnings

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from robots import ROBOTS

import torchcontact as tc
from torchcontact.cli import main
from torchcontact.contacts import ContactRecords, Contacts
from torchcontact.localize import Localizer, localize_chunk
from torchcontact.logs.format import (
    localization_fields,
    output_schema,
    read_contacts,
    read_log_columns,
    vectors,
)
from torchcontact.logs.simlog import simulated_table
from torchcontact.meshes import load_meshes
from torchcontact.simulation import simulate

pytest.importorskip("trimesh")
LINKS = ["panda_hand", "panda_leftfinger", "panda_rightfinger"]


@pytest.fixture(scope="module")
def panda():
    path = ROBOTS["panda"]()
    model = tc.RobotModel.from_urdf(path, keep_fixed=["panda_hand_joint"])
    model = model.with_ft_sensor("wrist_ft", "panda_hand_joint")
    return model, load_meshes(model, path, "collision", links=LINKS)


def test_simulated_log_without_skin_localized_chunk_and_estimate(panda):
    model, meshes = panda
    log = simulate(model, 300, sensor="wrist_ft", links=LINKS, max_contacts=1, seed=2,
                   surface=meshes.links, contact_fraction=0.7)  # fmt: skip
    table = simulated_table(log, skin=False)
    assert "true_contacts" in table.column_names
    skin, _, _ = read_contacts(table.column("contacts"))
    truth, fields, _ = read_contacts(table.column("true_contacts"))
    assert len(skin) == 0 and len(truth) > 100
    # the simulated normals are the meshes' outward normals, the forces push within the cone
    f_true = vectors(fields["true_force"], 3)[0]
    cos = -(f_true * truth.normals).sum(1) / np.linalg.norm(f_true, axis=1)
    assert (cos > np.cos(0.62) - 1e-9).all()

    # ---- the chunk as the pipeline decodes it; one frame has a skin contact on the hand
    N = table.num_rows
    q, qd, qdd = (vectors(table.column(c), model.nv)[0] for c in ("q", "qd", "qdd"))
    ft = {"wrist_ft": vectors(table.column("ft.wrist_ft"), 6)[0]}
    touched = np.flatnonzero(np.bincount(truth.frame, minlength=N) > 0)
    skin_frame = int(touched[0])
    skin = ContactRecords([skin_frame], ["panda_hand"], ["force"], np.zeros((1, 3)))
    loc = Localizer(model, meshes, links=LINKS, sensors=["wrist_ft"], force_threshold=0.5)
    out = localize_chunk(loc, q, qd, qdd, ft, skin, ft_covariance={"wrist_ft": np.eye(6) * 1e-4})
    code = out.columns["localize_status_code.wrist_ft"].to_numpy()
    assert code[skin_frame] & 32
    assert list(out.columns) == [n for n, _ in localization_fields(["wrist_ft"])]
    # the columns fit the output schema
    schema = output_schema(model.joint_names, ["wrist_ft"], [], {}, localize=["wrist_ft"])
    for name, col in out.columns.items():
        assert col.type == schema.field(name).type and len(col) == N
    # records: the skin one kept (source 0), one force record per localized frame, by frame
    rec = out.records
    assert np.all(np.diff(rec.frame) >= 0)
    assert (out.source == 0).sum() == 1 and rec.frame[out.source == 0][0] == skin_frame
    added = out.source < 0
    ok = (code == 0) | (code == 128) | (code == 64)
    assert sorted(rec.frame[added]) == sorted(np.flatnonzero(ok))
    no_contact = np.setdiff1d(np.arange(N), truth.frame)
    assert (code[no_contact] & 2).all()  # the free frames: force below the threshold
    # exact readings: where the line enters once, the point is the truth
    exact = np.flatnonzero(code == 0)
    assert len(exact) > 20  # (a few contact segments, each of many frames)
    tf = dict(zip(truth.frame.tolist(), range(len(truth)), strict=True))
    pos = {f: p for f, p in zip(rec.frame[added], rec.positions[added], strict=True)}
    links = {f: k for f, k in zip(rec.frame[added], rec.links[added], strict=True)}
    for f in exact:
        assert links[f] == truth.links[tf[f]]
        np.testing.assert_allclose(pos[f], truth.positions[tf[f]], atol=1e-7)

    # ---- the estimator on the filled-in records: the true force where localized exactly
    contacts, _ = Contacts.from_records(rec, N)
    est = tc.ContactEstimator(model, ["wrist_ft"])
    t = torch.tensor
    r = est.estimate(t(q), t(qd), t(qdd), {"wrist_ft": t(ft["wrist_ft"])}, contacts)
    got = np.zeros((N, 3))
    act = contacts.active.numpy()
    force = r.force.numpy()
    for f in exact:
        k = [i for i in range(contacts.K) if act[f, i] and contacts.links[i] == links[f]][0]
        got[f] = force[f, k]
    np.testing.assert_allclose(got[exact], f_true[[tf[f] for f in exact]], atol=1e-6)
    assert r.status.numpy()[exact].max() == 0


@pytest.fixture(scope="module")
def icub_noskin(tmp_path_factory):
    """``simulate --no-skin --on-collision-mesh``: 400 frames on the iCub forearm and hand."""
    out = tmp_path_factory.mktemp("icub") / "noskin.parquet"
    icub = str(ROBOTS["icub"]())
    args = ["simulate", "--robot", icub, "--sensor", "l_arm_ft", "--contact-links",
            "l_forearm,l_hand", "--frames", "400", "--max-contacts", "1", "--no-skin",
            "--on-collision-mesh", "--quiet", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    return out


def test_simulate_cli_no_skin_on_collision_mesh(icub_noskin, tmp_path):
    out, icub = icub_noskin, str(ROBOTS["icub"]())
    skin = read_log_columns(out, ["contacts"])["contacts"]
    truth = read_contacts(pq.read_table(out, columns=["true_contacts"]).column(0))[0]
    assert len(skin) == 0 and len(truth) > 0
    assert set(truth.links) <= {"l_forearm", "l_hand"}
    # a contact link without a collision mesh is refused with one message
    bad = ["simulate", "--robot", icub, "--sensor", "l_arm_ft", "--contact-links",
           "l_forearm,l_forearm_dh_frame", "--frames", "5", "--on-collision-mesh", "--out",
           str(tmp_path / "x.parquet")]  # fmt: skip
    assert main(bad) == 2
    assert not (tmp_path / "x.parquet").exists()


# ---------------------------------------------------------------------- estimate --localize
@pytest.fixture(scope="module")
def noskin_log(panda, tmp_path_factory):
    """300 frames on the panda's collision meshes, no skin (truth in ``true_contacts``)."""
    from torchcontact.logs import write_simulated_log

    model, meshes = panda
    path = tmp_path_factory.mktemp("noskin") / "log.parquet"
    return write_simulated_log(model, 300, path, seed=2, sensor="wrist_ft", links=LINKS,
                               max_contacts=1, surface=meshes.links, contact_fraction=0.7,
                               skin=False, temperature=False)  # fmt: skip


def test_estimate_localize_against_truth_chunks_and_resume(panda, noskin_log, tmp_path,
                                                           monkeypatch):  # fmt: skip
    """``estimate_file(localize=...)``: the localized records are the simulated truth (point,
    link, force), the columns and summary agree, and chunks or a resumed run give the same
    rows."""
    from torchcontact.logs import chunks
    from torchcontact.logs import format as fmt
    from torchcontact.logs.pipeline import LogLocalize, estimate_file

    model, meshes = panda
    loc = LogLocalize(meshes, LINKS, force_threshold=0.5, ft_std=[0.1] * 3 + [0.005] * 3)
    ref = tmp_path / "ref.parquet"
    s = estimate_file(noskin_log, model, ref, localize=loc, batch_size=300)
    out = pq.read_table(ref)
    log = pq.read_table(noskin_log)
    code = out.column("localize_status_code.wrist_ft").to_numpy()
    truth, tfields, _ = read_contacts(log.column("true_contacts"))
    got, gfields, _ = read_contacts(out.column("contacts"))
    # one record per localized frame (the log has no skin), at the truth where unambiguous
    used = (code & ~(64 | 128)) == 0
    assert sorted(got.frame) == sorted(np.flatnonzero(used)) and used.sum() > 40
    assert s["localize"]["wrist_ft"]["localized"] == used.sum()
    st = s["localize"]["wrist_ft"]["status"]
    assert st["NO_CONTACT"] == (code & 2 != 0).sum() > 10 and st["SKIN_CONTACT"] == 0
    assert s["localize_links"] == LINKS and s["bad_frames"] == 0
    t_at = dict(zip(truth.frame.tolist(), range(len(truth)), strict=True))
    exact = [i for i, f in enumerate(got.frame) if code[f] == 0]
    assert len(exact) > 30
    ti = [t_at[int(got.frame[i])] for i in exact]
    assert (got.links[exact] == truth.links[ti]).all() and set(got.kinds) == {"force"}
    np.testing.assert_allclose(got.positions[exact], truth.positions[ti], atol=1e-7)
    np.testing.assert_allclose(got.normals[exact], truth.normals[ti], atol=1e-6)
    f_got = vectors(gfields["force"], 3)[0][exact]
    np.testing.assert_allclose(f_got, vectors(tfields["true_force"], 3)[0][ti], atol=1e-6)
    pos = vectors(out.column("localize_position.wrist_ft"), 3)[0]
    np.testing.assert_allclose(pos[got.frame[exact]], got.positions[exact])
    std = out.column("localize_position_std.wrist_ft").to_numpy()
    assert np.isfinite(std[got.frame]).all() and (std[got.frame] > 0).all()
    assert b"torchcontact.localize" in out.schema.metadata
    # ---- a log without a contacts column: the same estimate, and no contact-free warning
    bare = tmp_path / "bare.parquet"
    pq.write_table(log.drop_columns(["contacts", "true_contacts"]), bare)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        estimate_file(bare, model, tmp_path / "b.parquet", localize=loc, batch_size=300)
    b = pq.read_table(tmp_path / "b.parquet")
    assert [f.name for f in b.schema.field("contacts").type.value_type] == [
        "link", "kind", "position", "normal", "force", "moment"]  # fmt: skip
    for name in ("joint_torques", "localize_status_code.wrist_ft"):
        assert b.column(name).equals(out.column(name))
    np.testing.assert_array_equal(read_contacts(b.column("contacts"))[0].positions, got.positions)
    # ---- chunks of 64 frames: the same rows; an interrupted run resumed: the same bytes
    small = tmp_path / "small.parquet"
    estimate_file(noskin_log, model, small, localize=loc, batch_size=64)
    reader = tmp_path / "reader.parquet"  # localized on the reader thread: the same rows too
    monkeypatch.setattr(chunks, "LOCALIZE_ON_READER", True)
    estimate_file(noskin_log, model, reader, localize=loc, batch_size=64)
    monkeypatch.undo()
    for again in (pq.read_table(small), pq.read_table(reader)):
        for name in out.column_names:  # (repr: NaN equals NaN, floats to the last bit)
            assert repr(again[name].to_pylist()) == repr(out[name].to_pylist()), name
    part = tmp_path / "part.parquet"
    real, calls = fmt.PartsWriter.append, []

    def interrupted(self, encoded, *a, **k):
        calls.append(1)
        if len(calls) > 2:
            raise KeyboardInterrupt
        return real(self, encoded, *a, **k)

    monkeypatch.setattr(fmt.PartsWriter, "append", interrupted)
    with pytest.raises(KeyboardInterrupt):
        estimate_file(noskin_log, model, part, localize=loc, batch_size=64)
    monkeypatch.undo()
    other = LogLocalize(meshes, LINKS, force_threshold=0.6)
    with pytest.raises(tc.errors.LogError, match="other inputs or options"):
        estimate_file(noskin_log, model, part, localize=other, batch_size=64, resume=True)
    r = estimate_file(noskin_log, model, part, localize=loc, batch_size=64, resume=True)
    assert r["resumed_chunks"] >= 2 and r["localize"] == s["localize"]
    assert part.read_bytes() == small.read_bytes()


def test_estimate_localize_cli_errors(tmp_path, capsys, monkeypatch):
    """--localize without collision meshes, with the meshes extra missing, or with its options
    alone: one ``error:`` line naming what is missing, nothing written."""
    from torchcontact.logs import write_simulated_log

    arm = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    log = write_simulated_log(arm, 5, tmp_path / "arm.parquet", robot="tcarm")
    base = ["estimate", str(log), "--quiet", "--out", str(tmp_path / "o.parquet")]
    assert main([*base, "--localize", "subtree"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --localize:") and "has no collision mesh" in err
    assert err.count("\n") == 1
    assert main([*base, "--localize-threshold", "2"]) == 2
    assert "--localize-threshold apply with --localize only" in capsys.readouterr().err
    icub = str(ROBOTS["icub"]())
    monkeypatch.setitem(__import__("sys").modules, "trimesh", None)  # the extra is missing
    assert main([*base, "--robot", icub, "--localize", "l_hand"]) != 0
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "pip install 'torchcontact[meshes]'" in err
    assert not list(tmp_path.glob("o.parquet*"))


def test_ray_worker_rebuilds_the_localization(icub_noskin):
    """The Ray engine's workers rebuild the log's estimator from picklable arguments: the
    localization's options travel, the meshes are loaded again from the URDF, and a worker's
    rows equal the driver-side estimator's (the local engine's per-chunk code)."""
    from torchcontact.logs.chunks import decoded_chunks, estimate_stream
    from torchcontact.logs.format import iter_chunks
    from torchcontact.logs.pipeline import load_robot, prepare, run_localize
    from torchcontact.logs.ray_worker import _worker_state, worker_args

    urdf = str(ROBOTS["icub"]())
    model = load_robot(urdf)
    opts = {"links": ["l_forearm", "l_hand"], "accept_ambiguous": True, "force_threshold": 0.5,
            "temporal": True}  # fmt: skip
    loc = run_localize(opts, model, urdf)
    pf, le, columns, _ = prepare(icub_noskin, model, ["l_arm_ft"], localize=loc)
    job = {"threads": 0, "dtype": "float64", "device": "cpu", "residual": None,
           "whole_log_segment": le.decoder.whole_log_segment}  # fmt: skip
    robot = {"robot": urdf, "ft_sensors": [], "identity": model.identity.sha256,
             "identity_entries": model.identity.to_json()}  # the setup worker's  # fmt: skip
    le2, _ = _worker_state(str(icub_noskin), robot, worker_args(le, icub_noskin), job)
    assert le2.localize is not loc and le2.localize.options() == loc.options()
    assert le2.localize.temporal is True
    assert le2.localizer.links == le.localizer.links and le2.layout == le.layout
    assert ("l_hand", "force") in zip(le.layout.links, le.layout.kinds, strict=True)
    assert le2.output_schema().equals(le.output_schema(), check_metadata=True)
    tables = list(iter_chunks(pf, columns, 400, str(icub_noskin)))
    a, b = (next(estimate_stream(x, decoded_chunks(x, iter(tables), 5), None, "eager"))
            for x in (le, le2))  # fmt: skip
    for name in a.column_names:
        assert repr(a.column(name).to_pylist()) == repr(b.column(name).to_pylist()), name
    code = a.column("localize_status_code.l_arm_ft").to_numpy()
    assert ((code == 0) | (code == 16)).sum() > 100  # localized frames (a few ambiguous)
