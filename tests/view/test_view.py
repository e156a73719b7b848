"""``torchcontact view``: recordings read back with rerun's own reader (``rerun.chunk.RrdReader``).

The logs are small simulated logs of the bundled tcarm (``torchcontact.simulation``, seeded): one
or two pure-force contacts on its skin patches, so two-contact frames are rank-deficient (6
unknowns, rank 5). What is checked comes from outside the view: the estimate's Parquet columns,
a forward pass of the model, and the estimator's own prediction of the readings.
"""

from __future__ import annotations

import json
import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

import torchcontact as tc
from torchcontact.cli import main
from torchcontact.drivers.live import pack_joint_state
from torchcontact.logs import estimate_file, write_simulated_log
from torchcontact.logs.format import read_contacts, vectors, write_table
from torchcontact.logs.plot import TRUTH_ALPHA, slot_rgb
from torchcontact.robots import tcarm_path
from torchcontact.simulation import UnmodeledEffects

rr = pytest.importorskip("rerun")
pytest.importorskip("trimesh")

FRAMES = 240
#: float32 in the recording: arrows and positions to this relative tolerance
F32 = dict(rtol=2e-6, atol=2e-6)


@pytest.fixture(scope="module")
def model():
    return tc.RobotModel.from_urdf(tcarm_path())


@pytest.fixture(scope="module")
def logs(model, tmp_path_factory):
    d = tmp_path_factory.mktemp("view")
    noise = UnmodeledEffects(noise_std=(0.05,) * 6)  # N, N m: a residual to draw
    log = write_simulated_log(model, FRAMES, d / "log.parquet", seed=21, effects=noise)
    est = estimate_file(log, model, d / "est.parquet")["output"]
    return d, Path(log), Path(est)


def read_rrd(path) -> dict[str, list[pa.RecordBatch]]:
    """Entity path -> record batches of its chunks (rerun's reader)."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def rows_of(batches, component) -> dict[int, object]:
    """``frame`` -> the component's value at that frame (chunks on the ``frame`` timeline)."""
    out = {}
    for b in batches:
        if component in b.schema.names and "frame" in b.schema.names:
            for f, v in zip(
                b.column("frame").to_pylist(), b.column(component).to_pylist(), strict=False
            ):
                out[f] = v
    return out


def static(batches, component):
    return next(
        b.column(component).to_pylist()[0]
        for b in batches
        if component in b.schema.names and "frame" not in b.schema.names
    )


def world_contacts(model, log, est, f):
    """Contact points, estimated and true forces of row ``f`` in the world frame (independent
    of the view: the estimate's columns and a forward pass at the log's q)."""
    q = torch.tensor(np.asarray(pq.read_table(log, columns=["q"])["q"][f].as_py()))[None]
    fp = tc.forward_pass(model, q, torch.zeros_like(q), torch.zeros_like(q))
    records, fields, _ = read_contacts(
        pq.read_table(est, columns=["contacts"])["contacts"][f : f + 1]
    )
    force = vectors(fields["force"], 3)[0]
    truth = vectors(fields["true_force"], 3)[0]
    pts, fw, tw = [], [], []
    for i, link in enumerate(records.links):
        R, p = (x[0].numpy() for x in model.frame_pose(fp, link))
        pts.append(R @ records.positions[i] + p)
        fw.append(R @ force[i])
        tw.append(R @ truth[i])
    return np.array(pts), np.array(fw), np.array(tw), records


@pytest.fixture(scope="module")
def recording(logs):
    d, log, est = logs
    out = d / "view.rrd"
    summary = view_log_(log, est, out)
    return summary, read_rrd(out)


def view_log_(log, est, out, **kw):
    from torchcontact.view import view_log

    # batches of 100 frames: the log streams through in three chunks
    return view_log(log, est, tcarm_path(), out, nullspace=True, batch_size=100, **kw)


def test_recording_entities_and_frames(model, logs, recording):
    from torchcontact.meshes import load_meshes

    _, log, _ = logs
    summary, ents = recording
    assert summary["frames"] == FRAMES and summary["rows"] == [0, FRAMES - 1]
    # the robot: one posed entity per body, a visual mesh per link with <visual>, in its frame
    meshes = load_meshes(model, tcarm_path(), "visual")
    assert len(meshes.links) == 12 and meshes.missing == ()
    for link, lm in meshes.links.items():
        path = f"/world/robot/{model.body_names[lm.body]}/{link}"
        v = np.array(static(ents[path], "Mesh3D:vertex_positions"))
        np.testing.assert_allclose(v, lm.vertices, **F32)
        np.testing.assert_allclose(
            np.array(static(ents[path], "Transform3D:translation"))[0], lm.p_body_link, **F32
        )
    expected = {
        "/world/contacts/points",
        "/world/contacts/estimate",
        "/world/contacts/truth",
        "/world/robot/ft_plate/ft_base_ft/measured",
        "/world/robot/ft_plate/ft_base_ft/residual",
        "/world/nullspace/base_ft/dir0",
        "/plots/forces/slot0/estimate",
        "/plots/forces/slot0/truth",
        "/plots/identifiability/base_ft/rank",
        "/plots/identifiability/base_ft/unknowns",
        "/plots/identifiability/base_ft/nullity",
        "/plots/identifiability/ill_posed",
        "/plots/residual/base_ft",
        "/plots/sensors/base_ft/measured",
        "/plots/sensors/base_ft/residual",
        "/plots/status/code",
        "/states/status",
        "/states/posedness",
        "/log",
        "/legend",
    }
    assert expected <= set(ents), expected - set(ents)
    assert not any("skeleton" in e for e in ents)  # every mesh found: no stick figure
    # every frame is drawn, on the log's time line
    t_ns = pq.read_table(log, columns=["t_ns"])["t_ns"].to_numpy()
    for b in model.body_names:
        pose = rows_of(ents[f"/world/robot/{b}"], "Transform3D:translation")
        assert sorted(pose) == list(range(FRAMES))
    times = {}
    for batch in ents["/world/robot/hand"]:
        if "frame" in batch.schema.names:
            times.update(
                zip(
                    batch.column("frame").to_pylist(),
                    batch.column("time").cast(pa.int64()).to_pylist(),
                    strict=False,
                )
            )
    assert [times[f] for f in range(FRAMES)] == t_ns.tolist()
    legend = static(ents["/legend"], "TextDocument:text")[0]
    assert f"{summary['scale']:g} N per m" in legend


def test_contact_arrows_equal_the_estimate_and_ill_posed_status(model, logs, recording):
    _, log, est = logs
    summary, ents = recording
    scale = summary["scale"]
    tab = pq.read_table(est)
    ill = tab["rank.base_ft"].to_numpy() < tab["unknowns.base_ft"].to_numpy()
    two = np.array([len(c) == 2 for c in tab["contacts"].to_pylist()])
    ok = tab["status_code"].to_numpy() == 0
    f = int(np.flatnonzero(two & ill & ok)[len(np.flatnonzero(two & ill & ok)) // 2])
    pts, fw, tw, records = world_contacts(model, log, est, f)
    assert np.abs(fw).max() > 0.1  # a real force, not zeros
    origins = np.array(rows_of(ents["/world/contacts/estimate"], "Arrows3D:origins")[f])
    arrows = np.array(rows_of(ents["/world/contacts/estimate"], "Arrows3D:vectors")[f])
    truth = np.array(rows_of(ents["/world/contacts/truth"], "Arrows3D:vectors")[f])
    colors = rows_of(ents["/world/contacts/estimate"], "Arrows3D:colors")[f]
    tcolors = rows_of(ents["/world/contacts/truth"], "Arrows3D:colors")[f]
    order = np.arange(len(records))  # arrows in the estimate's record order
    np.testing.assert_allclose(origins, pts[order], **F32)
    np.testing.assert_allclose(arrows * scale, fw[order], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(truth * scale, tw[order], rtol=1e-5, atol=1e-5)
    # one colour per slot, the truth in the same colour, lighter
    slots = json.loads(json.dumps(summary["layout"]))
    k = [slots.index(str(records.links[i])) for i in order]

    def rgba(c):
        return tuple(int(c).to_bytes(4, "big"))

    assert [rgba(c) for c in colors] == [slot_rgb(x) for x in k]
    assert [rgba(c) for c in tcolors] == [slot_rgb(x, TRUTH_ALPHA) for x in k]
    assert len(set(k)) == 2
    # the frame is marked ill-posed, its status is ok, its null space is one direction
    assert rows_of(ents["/plots/identifiability/ill_posed"], "Scalars:scalars")[f] == [1.0]
    assert rows_of(ents["/plots/status/code"], "Scalars:scalars")[f] == [0.0]
    assert rows_of(ents["/plots/identifiability/base_ft/nullity"], "Scalars:scalars")[f] == [1.0]
    lane = rows_of(ents["/states/posedness"], "StateChange:state")
    assert lane[max(r for r in lane if r <= f)] == ["ill-posed"]
    well = int(np.flatnonzero(~ill & ok & (tab["unknowns.base_ft"].to_numpy() > 0))[0])
    assert lane[max(r for r in lane if r <= well)] == ["well-posed"]
    # its null-space direction: opposite forces at the two contacts (no reading changes)
    null = np.array(rows_of(ents["/world/nullspace/base_ft/dir0"], "Arrows3D:vectors")[f])
    at = np.array(rows_of(ents["/world/nullspace/base_ft/dir0"], "Arrows3D:origins")[f])
    assert null.shape == (2, 3) and np.linalg.norm(null[0]) > 0.01
    np.testing.assert_allclose(null.sum(0), 0, atol=1e-6)
    np.testing.assert_allclose(sorted(at.tolist()), sorted(pts.tolist()), **F32)
    after = int(np.flatnonzero(~ill & (np.arange(FRAMES) > f))[0])  # cleared when well-posed
    assert rows_of(ents["/world/nullspace/base_ft/dir0"], "Arrows3D:vectors")[after] == []


def test_residual_is_the_predicted_minus_the_measured_reading(logs, recording):
    """|A x - b| drawn per component equals the estimator's own residual.base_ft column."""
    _, log, est = logs
    _, ents = recording
    tab = pq.read_table(est)
    res = rows_of(ents["/plots/sensors/base_ft/residual"], "Scalars:scalars")
    meas = rows_of(ents["/plots/sensors/base_ft/measured"], "Scalars:scalars")
    ft = vectors(pq.read_table(log, columns=["ft.base_ft"])["ft.base_ft"], 6)[0]
    ok = np.flatnonzero(tab["status_code"].to_numpy() == 0)
    assert len(ok) > FRAMES // 2
    drawn = np.array([res[f] for f in ok])
    np.testing.assert_allclose(
        np.linalg.norm(drawn, axis=1), tab["residual.base_ft"].to_numpy()[ok], rtol=1e-6, atol=1e-9
    )
    assert np.abs(drawn).max() > 1e-3  # the simulated noise leaves a residual
    np.testing.assert_allclose(np.array([meas[f] for f in ok]), ft[ok])


def test_cli_every_window_and_printed_summary(logs, tmp_path, capsys):
    _, log, est = logs
    out = tmp_path / "w.rrd"
    args = [
        "view",
        str(log),
        str(est),
        "--out",
        str(out),
        "--every",
        "4",
        "--start",
        "0.5",
        "--end",
        "1.5",
        "--quiet",
    ]
    assert main(args) == 0
    printed = capsys.readouterr().out
    t = (pq.read_table(log, columns=["t_ns"])["t_ns"].to_numpy() - 0) * 1e-9
    inside = np.flatnonzero((t - t[0] >= 0.5) & (t - t[0] <= 1.5))
    want = list(range(inside[0], inside[-1] + 1, 4))
    assert f"drew {len(want)} frames (rows {inside[0]}-{inside[-1]}, every 4)" in printed
    assert f"rerun {out}" in printed
    ents = read_rrd(out)
    assert sorted(rows_of(ents["/world/robot/hand"], "Transform3D:translation")) == want
    assert not Path(str(out) + ".tmp").exists()


def test_bad_input_is_one_error_line(model, logs, tmp_path, capsys):
    _, log, est = logs

    def error(args, code):
        assert main(["view", *map(str, args)]) == code
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), err
        return err[0]

    table = pq.read_table(log)
    shifted = tmp_path / "other.parquet"
    t = pa.array(table["t_ns"].to_numpy() + 5_000_000)
    write_table(table.set_column(0, "t_ns", t), shifted)
    out = tmp_path / "x.rrd"
    msg = error([shifted, est, "--out", out], 1)
    assert "t_ns of row 0 differ" in msg and "another log" in msg
    empty = tmp_path / "empty.parquet"
    write_table(table.slice(0, 0), empty)
    assert "no frames to view" in error([empty, "--out", out], 1)
    assert "--every must be an integer >= 1" in error([log, est, "--out", out, "--every", "0"], 2)
    assert "no frame of" in error([log, est, "--out", out, "--start", "99"], 2)
    assert "not an output of torchcontact estimate" in error([log, log, "--out", out], 1)
    assert "is the input" in error([log, est, "--out", est], 2)
    assert not out.exists() and not Path(str(out) + ".tmp").exists()


def test_missing_meshes_draw_link_frames_and_are_named_once(logs, tmp_path, capsys):
    """A URDF whose mesh cannot be found: a warning naming it, link frames and the stick figure
    drawn; ``--require-meshes`` makes it one error line."""
    _, log, _ = logs
    text = tcarm_path().read_text()
    mesh = (
        '<visual><geometry><mesh filename="package://nope/meshes/flange.stl"/></geometry></visual>'
    )
    text = text.replace('<link name="tool"/>', f'<link name="tool">{mesh}</link>')
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(text)
    out = tmp_path / "m.rrd"
    assert main(["view", str(log), "--robot", str(urdf), "--out", str(out), "--every", "40"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: ") and "tool: flange.stl" in err[0], err
    ents = read_rrd(out)
    assert static(ents["/world/robot/hand/tool"], "TransformAxes3D:axis_length")[0] > 0
    assert "Mesh3D:vertex_positions" not in {
        n for b in ents["/world/robot/hand/tool"] for n in b.schema.names
    }
    assert len(rows_of(ents["/world/robot/skeleton"], "LineStrips3D:strips")) == FRAMES // 40
    assert "Mesh3D:vertex_positions" in ents["/world/robot/hand/hand"][0].schema.names
    assert (
        main(["view", str(log), "--robot", str(urdf), "--out", str(out), "--require-meshes"]) == 1
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "flange.stl" in err[0], err


def test_log_to_rerun_from_python_and_continued_streams(model, tmp_path):
    from torchcontact.view import log_to_rerun

    B = 4
    q = torch.linspace(-0.3, 0.4, B * model.nv, dtype=torch.float64).reshape(B, model.nv)
    zero = torch.zeros_like(q)
    pos = torch.tensor([[0.01, 0.0, 0.0], [0.0, 0.02, 0.0]], dtype=torch.float64).expand(B, 2, 3)
    push = torch.tensor([[1.0, 0.5, -4.0, 0, 0, 0], [0.0, -1.0, -2.0, 0, 0, 0]]).double()
    links = ("forearm_skin", "hand_skin")
    est = tc.ContactEstimator(model, backend="eager")
    ft = est.predict_ft(
        q, zero, zero, tc.Contacts(links, ("known",) * 2, pos, wrenches=push.expand(B, 2, 6))
    )
    active = torch.tensor([[True, False], [True, True], [False, True], [True, False]])
    contacts = tc.Contacts(links, ("force", "force"), pos, active=active)
    r = est.estimate(q, zero, zero, ft, contacts)
    rec = rr.RecordingStream("test", recording_id="a1b2")
    path = tmp_path / "nb.rrd"
    rec.save(path)
    frames = {"t_ns": np.arange(B) * 10**7, "q": q, "ft": ft, "contacts": contacts}
    scene = log_to_rerun(model, frames, r, recording=rec, urdf=tcarm_path(), scale=10.0)
    frames2 = {**frames, "t_ns": frames["t_ns"] + B * 10**7}
    assert log_to_rerun(model, frames2, r, scene=scene) is scene
    rec.flush()
    rec.disconnect()
    ents = read_rrd(path)
    arrows = rows_of(ents["/world/contacts/estimate"], "Arrows3D:vectors")
    assert sorted(arrows) == list(range(2 * B))  # the second call continues the rows
    fp = tc.forward_pass(model, q, zero, zero)
    for f in range(2 * B):
        b = f % B
        want = [
            model.frame_pose(fp, links[k])[0][b].numpy() @ r.force[b, k].numpy() / 10.0
            for k in range(2)
            if active[b, k]
        ]
        np.testing.assert_allclose(np.array(arrows[f]), np.array(want), rtol=1e-5, atol=1e-6)
    assert rows_of(ents["/plots/identifiability/ill_posed"], "Scalars:scalars")[1] == [1.0]


def test_live_loop_view_draws_each_frame(model, tmp_path):
    """The live loop's ``on_frame`` hook (``run --view``) with a :class:`LiveView`: every frame's
    contact forces are drawn as the estimator returned them (a stand-in for the ONNX runtime that
    answers with the torch estimator, the same dict keys)."""
    from torchcontact.contacts import SlotLayout
    from torchcontact.drivers.base import FTSource, SampleFlags
    from torchcontact.drivers.live import JointState, LiveLoop
    from torchcontact.view.scene import LiveView, RerunScene

    links, kinds = ("forearm_skin", "hand_skin"), ("force", "force")
    pos = np.array([[0.0, 0.01, 0.0], [0.02, 0.0, 0.0]])
    est = tc.ContactEstimator(model, backend="eager")
    q0 = np.linspace(0.1, -0.2, model.nv)
    qt = torch.tensor(q0)[None]
    zero = torch.zeros_like(qt)
    n = 6
    forces = [np.array([[0.2 * i, 0, -3.0], [0, 0, 0]]) for i in range(n)]
    readings = []
    for f in forces:
        w = torch.tensor(np.concatenate([f, np.zeros((2, 3))], 1))[None]
        c = tc.Contacts(links, ("known",) * 2, torch.tensor(pos)[None], wrenches=w)
        readings.append(est.predict_ft(qt, zero, zero, c)["base_ft"][0].numpy())

    class Replay(FTSource):
        def _connect(self):
            self.i = 0

        def _disconnect(self):
            pass

        def _receive(self, timeout):
            if self.i >= n:
                return None
            self.i += 1
            return 10**9 + self.i * 10**7, readings[self.i - 1], 0, SampleFlags.NONE

    def estimator(q, qd, qdd, ft):
        r = est.estimate(
            torch.tensor(q)[None],
            zero,
            zero,
            {"base_ft": torch.tensor(ft)[None]},
            tc.Contacts(
                links, kinds, torch.tensor(pos)[None], active=torch.tensor([[True, False]])
            ),
        )
        return {
            "force": r.force[0].numpy(),
            "moment": r.moment[0].numpy(),
            "rank": [int(r.rank["base_ft"])],
            "unknowns": [int(r.unknowns["base_ft"])],
            "residual": [float(r.residual["base_ft"])],
            "status": int(r.status),
        }

    out = tmp_path / "live.rrd"
    scene = RerunScene(model, urdf=tcarm_path(), layout=SlotLayout(links, kinds), scale=20.0)
    scene.recording.save(str(out) + ".tmp")
    view = LiveView(
        scene, ["base_ft"], contacts={"positions": pos, "active": [1, 0]}, every=4, out=out
    )
    joints = JointState(0, 0, q0, np.zeros_like(q0), np.zeros_like(q0))
    src = Replay("base_ft")
    src.open()
    summary = LiveLoop(src, lambda: joints, estimator, [], on_frame=view).run(max_frames=n)
    view.close()
    assert summary["published"] == n
    ents = read_rrd(out)
    arrows = rows_of(ents["/world/contacts/estimate"], "Arrows3D:vectors")
    assert sorted(arrows) == list(range(n))
    R = model.frame_pose(tc.forward_pass(model, qt, zero, zero), links[0])[0][0].numpy()
    for i in range(n):
        np.testing.assert_allclose(np.array(arrows[i])[0] * 20.0, R @ forces[i][0], atol=1e-5)


@pytest.mark.parametrize(
    "robot, links",
    [("panda", ("panda_link0", "panda_link4", "panda_hand", "panda_leftfinger")), ("icub", None)],
)
def test_robot_meshes_of_installed_packages(robot, links, tmp_path):
    """iCub (icub-models) and the panda (example-robot-data, COLLADA files with colours; a few
    links, they load slowly): every visual mesh is found through the installed packages and drawn
    in its link frame, posed by q."""
    from robots import ROBOTS

    from torchcontact.view.scene import RerunScene

    urdf = ROBOTS[robot]()
    m = tc.RobotModel.from_urdf(urdf)
    scene = RerunScene(m, urdf=urdf, sensors=[], links=links)
    out = tmp_path / f"{robot}.rrd"
    scene.recording.save(out)
    q = np.zeros((2, m.nv))
    q[1] = 0.3
    from torchcontact.view import ViewFrames

    scene.log(ViewFrames(t_ns=[0, 10**7], q=q))
    scene.recording.flush()
    scene.recording.disconnect()
    assert scene.missing == () and len(scene.meshes.links) == (len(links) if links else 39)
    if robot == "panda":  # the COLLADA materials give vertex colours
        assert scene.meshes.links["panda_link4"].vertex_colors is not None
    ents = read_rrd(out)
    meshes = [
        e for e, bs in ents.items() if any("Mesh3D:vertex_positions" in b.schema.names for b in bs)
    ]
    assert len(meshes) == len(scene.meshes.links)
    fp = tc.forward_pass(
        m,
        torch.tensor(q),
        torch.zeros(2, m.nv, dtype=torch.float64),
        torch.zeros(2, m.nv, dtype=torch.float64),
    )
    b = m.nb - 1
    pose = rows_of(ents[f"/world/robot/{m.body_names[b]}"], "Transform3D:translation")
    np.testing.assert_allclose(np.array(pose[1])[0], fp.p[1, b].numpy(), **F32)


def test_run_view_draws_every_published_frame(tmp_path, capsys):
    """``torchcontact run --onnx ... --view FILE.rrd``: the bundled tcarm's estimator exported
    (slots forearm_skin and hand_skin), a simulated Modbus sensor serving the reading the model
    predicts for a known force on hand_skin, joint states over UDP: every published frame is
    drawn, its arrow the published force."""
    pytest.importorskip("onnxruntime")
    LINKS, KINDS = ("forearm_skin", "hand_skin"), ("force", "force")
    POSITION, FORCE = [0.01, 0.02, 0.0], [1.5, -2.0, -6.0]  # m and N on hand_skin
    from torchcontact.drivers.simulator import TcpSimulator, constant_signal
    from torchcontact.export import export_estimator

    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    onnx = tmp_path / "tcarm.onnx"
    export_estimator(model, ["base_ft"], list(LINKS), list(KINDS), onnx)
    q = np.linspace(0.2, -0.4, model.nv)
    qt, zero = torch.tensor(q), torch.zeros(model.nv, dtype=torch.float64)
    contact = tc.Contacts(
        ["hand_skin"], ["known"], torch.tensor([POSITION]).double(),
        wrenches=torch.tensor([[*FORCE, 0.0, 0.0, 0.0]]).double(),
    )  # fmt: skip
    ft = (
        tc.ContactEstimator(model, backend="eager")
        .predict_ft(qt, zero, zero, contact)["base_ft"]
        .numpy()
    )
    sim = TcpSimulator(profile="generic-float32", signal=constant_signal(ft)).start()
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    spec = tmp_path / "contacts.json"
    spec.write_text(json.dumps({"contact": [{"link": "hand_skin", "position": POSITION}]}))
    stop = threading.Event()

    def send():
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        seq = 0
        while not stop.is_set():
            seq += 1
            tx.sendto(pack_joint_state(seq, 0, q, 0 * q, 0 * q), ("127.0.0.1", port))
            time.sleep(0.01)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    out = tmp_path / "live.rrd"
    try:
        rc = main(
            ["run", "--profile", "generic-float32", "--tcp", f"127.0.0.1:{sim.port}", "--onnx",
             str(onnx), "--robot", "tcarm", "--contacts", str(spec), "--joints",
             f"udp://127.0.0.1:{port}", "--require-joints", "--duration", "1.0", "--view",
             str(out)]
        )  # fmt: skip
    finally:
        stop.set()
        sender.join()
        sim.stop()
    assert rc == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(lines) > 3
    ents = read_rrd(out)
    legend = next(b.column("TextDocument:text").to_pylist()[0][0] for b in ents["/legend"])
    scale = float(re.search(r"\*\*([\d.e+]+) N per m\*\*", legend).group(1))
    arrows = rows_of(ents["/world/contacts/estimate"], "Arrows3D:vectors")
    assert sorted(arrows) == list(range(len(lines)))  # every published frame, in order
    fp = tc.forward_pass(model, qt[None], zero[None], zero[None])
    R = model.frame_pose(fp, "hand_skin")[0][0].numpy()
    for i, r in enumerate(lines):
        published = np.array(r["estimate"]["force"][1])
        np.testing.assert_allclose(published, FORCE, atol=2e-3)
        np.testing.assert_allclose(np.array(arrows[i])[0] * scale, R @ published, atol=1e-4)
    assert main(["run", "--tcp", "127.0.0.1:1", "--view", str(out)]) == 2
    assert "--view goes with --onnx" in capsys.readouterr().err


def test_constrained_estimate_draws_cones(model, logs, tmp_path):
    """A ``--constraints`` estimate: per frame the number of contacts whose cone binds, the
    iterations, and a convergence lane, as in the estimate's columns."""
    from torchcontact import FrictionCones
    from torchcontact.logs import LogConstraints
    from torchcontact.view import view_log

    _, log, _ = logs
    # the minimum-norm objective, whose solutions lie on the cones' boundaries where they bind
    # (the default MAP estimate is an interior point of the cones)
    cons = LogConstraints(FrictionCones(objective="min_norm"), friction=0.5)
    est = estimate_file(log, model, tmp_path / "c.parquet", constraints=cons)
    out = tmp_path / "c.rrd"
    view_log(log, est["output"], tcarm_path(), out, every=2)
    ents = read_rrd(out)
    tab = pq.read_table(est["output"])
    active = [sum(bool(c["cone_active"]) for c in row) for row in tab["contacts"].to_pylist()]
    drawn = rows_of(ents["/plots/cones/active"], "Scalars:scalars")
    assert sorted(drawn) == list(range(0, FRAMES, 2))
    assert [drawn[f][0] for f in range(0, FRAMES, 2)] == active[::2]
    assert max(active) >= 1  # some cone binds
    iters = rows_of(ents["/plots/cones/base_ft/iterations"], "Scalars:scalars")
    assert [iters[f][0] for f in range(0, FRAMES, 2)] == tab["iterations.base_ft"].to_pylist()[::2]
    lane = rows_of(ents["/states/cones/base_ft"], "StateChange:state")
    assert {v[0] for v in lane.values()} <= {"converged", "not converged", ""}
    assert "converged" in {v[0] for v in lane.values()}
    points = rows_of(ents["/world/contacts/cone_active"], "Points3D:positions")
    assert [len(points[f]) for f in range(0, FRAMES, 2)] == active[::2]
