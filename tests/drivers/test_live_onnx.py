"""The live loop with the exported estimator (``OnnxEstimator``, ``torchcontact run --onnx``).

The bundled tcarm's estimator is exported once (slots ``forearm_skin`` and ``hand_skin``, both
``force``). The simulated Modbus sensor serves the reading the rigid-body model predicts for a
known force on ``hand_skin`` at a fixed joint state (``ContactEstimator.predict_ft``), so the loop
must publish that force back; the float32 registers and the float32 graph bound the error.
"""

import json
import socket
import threading
import time

import numpy as np
import pytest
import torch

import torchcontact as tc
from torchcontact.cli import main
from torchcontact.drivers import ModbusFTSensor
from torchcontact.drivers.live import (
    LiveLoop,
    OnnxEstimator,
    UdpJointSource,
    pack_joint_state,
)
from torchcontact.drivers.simulator import constant_signal

pytest.importorskip("onnxruntime")

LINKS, KINDS = ("forearm_skin", "hand_skin"), ("force", "force")
POSITIONS = [[0.0, 0.0, 0.0], [0.01, 0.02, 0.015]]  # m, in each slot's link frame
FORCE = [1.5, -2.0, -6.0]  # N on hand_skin, in its frame


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from torchcontact.export import export_estimator

    torch.set_num_threads(1)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    path = tmp_path_factory.mktemp("onnx") / "tcarm.onnx"
    export_estimator(model, ["base_ft"], list(LINKS), list(KINDS), path)
    nv = model.nv
    q = np.linspace(0.2, -0.4, nv)
    zero = torch.zeros(nv, dtype=torch.float64)
    est = tc.ContactEstimator(model, ["base_ft"])
    contacts = tc.Contacts(
        LINKS,
        ("known", "known"),
        torch.tensor(POSITIONS, dtype=torch.float64),
        wrenches=torch.tensor([[0.0] * 6, [*FORCE, 0.0, 0.0, 0.0]], dtype=torch.float64),
        active=torch.tensor([False, True]),
    )
    ft = est.predict_ft(torch.tensor(q), zero, zero, contacts)["base_ft"].numpy()
    # torch reference of the same estimate (float64), for the joint torques
    ref = est.estimate(
        torch.tensor(q),
        zero,
        zero,
        {"base_ft": torch.tensor(ft)},
        tc.Contacts(
            LINKS, KINDS, torch.tensor(POSITIONS, dtype=torch.float64), active=torch.tensor([0, 1])
        ),
    )
    return {"model": model, "path": path, "q": q, "ft": ft, "ref": ref}


def _joints(q):
    src = UdpJointSource()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.sendto(pack_joint_state(1, 0, q, np.zeros_like(q), np.zeros_like(q)), src.address)
    time.sleep(0.05)
    return src


def _run_loop(src, q, est, frames):
    """``frames`` published records of the live loop on ``src`` (opened) with joints ``q``."""
    records = []

    class Keep:
        def publish(self, r):
            records.append(r)

    joints = _joints(q)
    try:
        summary = LiveLoop(src, joints, est, [Keep()], require_joints=True).run(
            max_frames=frames, duration=5.0
        )
    finally:
        src.close()
        joints.close()
    assert summary["published"] == frames and summary["estimator_errors"] == 0
    return records


def test_loop_publishes_forces_and_joint_torques(scene, tcp_sim):
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(scene["ft"]))
    ft = ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port)
    ft.open()
    est = OnnxEstimator(
        str(scene["path"]),
        {"positions": POSITIONS, "active": [0, 1]},
        expect_joint_names=scene["model"].joint_names,
    )
    records = _run_loop(ft, scene["q"], est, 10)
    ref_tau = scene["ref"].joint_torques.numpy()
    assert np.abs(ref_tau).max() > 0.1  # the contact loads the joints
    for r in records:
        e = r["estimate"]
        assert e["status"] == 0
        np.testing.assert_allclose(e["force"][1], FORCE, atol=2e-3)
        assert e["force"][0] == [0.0, 0.0, 0.0]  # inactive slot
        np.testing.assert_allclose(e["joint_torques"], ref_tau, atol=2e-3)


def test_default_contact_spec_is_no_contact(scene):
    est = OnnxEstimator(str(scene["path"]))
    z = np.zeros_like(scene["q"])
    out = est(scene["q"], z, z, scene["ft"])
    assert np.all(np.asarray(out["force"]) == 0)  # every slot inactive
    assert out["joint_torques"].shape == (scene["model"].nv,)
    assert np.all(np.isfinite(out["joint_torques"]))
    assert out["residual"][0] > 1.0  # the unexplained load shows in the F/T residual
    with pytest.raises(ValueError, match="joint state has 0 joints"):
        est(np.zeros(0), np.zeros(0), np.zeros(0), scene["ft"])
    with pytest.raises(ValueError, match="positions must have shape"):
        OnnxEstimator(str(scene["path"]), {"positions": [[0.0, 0.0, 0.0]]})


def test_run_cli_onnx(scene, tcp_sim, tmp_path, capsys):
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(scene["ft"]))
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    spec = tmp_path / "contacts.json"  # the contact-spec format of every command
    spec.write_text(json.dumps({"contact": [{"link": "hand_skin", "position": POSITIONS[1]}]}))
    stop = threading.Event()

    def send():
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        z, seq = np.zeros_like(scene["q"]), 0
        while not stop.is_set():
            seq += 1
            tx.sendto(pack_joint_state(seq, 0, scene["q"], z, z), ("127.0.0.1", port))
            time.sleep(0.01)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        rc = main(
            [
                "run",
                "--profile",
                "generic-float32",
                "--tcp",
                f"127.0.0.1:{sim.port}",
                "--onnx",
                str(scene["path"]),
                "--contacts",
                str(spec),
                "--joints",
                f"udp://127.0.0.1:{port}",
                "--require-joints",
                "--duration",
                "1.0",
            ]
        )
    finally:
        stop.set()
        sender.join()
    assert rc == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(lines) > 3
    for r in lines:
        np.testing.assert_allclose(r["estimate"]["force"][1], FORCE, atol=2e-3)
        assert len(r["estimate"]["joint_torques"]) == scene["model"].nv
    assert main(["run", "--tcp", "127.0.0.1:1", "--onnx", str(tmp_path / "none.onnx")]) == 2
    assert "no such file" in capsys.readouterr().err
    spec.write_text(json.dumps({"contact": [{"link": "upper_arm_skin", "position": [0, 0, 0]}]}))
    args = ["run", "--tcp", "127.0.0.1:1", "--onnx", str(scene["path"]), "--contacts", str(spec)]
    assert main(args) == 2  # a contact the graph has no slot for
    assert "['upper_arm_skin:force'] find no free slot" in capsys.readouterr().err


# ---------------------------------------------------------------- several sensors, residual, robot

TWO_LINKS, TWO_KINDS = ("hand_skin", "tool"), ("force", "wrench")
TOOL_WRENCH = [0.5, 1.0, -3.0, 0.02, -0.01, 0.03]  # on the tool, in its frame, about its origin


@pytest.fixture(scope="module")
def two_sensors(tmp_path_factory):
    """The arm with a second sensor on its tool flange: forces on the hand and the tool."""
    from torchcontact.export import export_estimator

    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path(), keep_fixed=["tool_joint"])
    model = model.with_ft_sensor("tool_ft", "tool_joint")
    path = tmp_path_factory.mktemp("onnx2") / "tcarm2.onnx"
    export_estimator(model, None, list(TWO_LINKS), list(TWO_KINDS), path)
    est = tc.ContactEstimator(model)
    q = np.linspace(0.3, -0.3, model.nv)
    zero = torch.zeros(model.nv, dtype=torch.float64)
    pos = torch.tensor([POSITIONS[1], [0.0, 0.0, 0.0]], dtype=torch.float64)
    given = tc.Contacts(
        TWO_LINKS,
        ("known", "known"),
        pos,
        wrenches=torch.tensor([[*FORCE, 0, 0, 0], TOOL_WRENCH], dtype=torch.float64),
    )
    ft = est.predict_ft(torch.tensor(q), zero, zero, given)
    return {
        "model": model,
        "path": path,
        "q": q,
        "pos": pos.numpy(),
        "ft": {k: v.numpy() for k, v in ft.items()},
    }


def _sender(q, port, stop):
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    z, seq = np.zeros_like(q), 0
    while not stop.is_set():
        seq += 1
        tx.sendto(pack_joint_state(seq, 0, q, z, z), ("127.0.0.1", port))
        time.sleep(0.01)


def _free_udp_port():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    return port


def test_several_sensors_in_one_graph(two_sensors, tcp_sim):
    from torchcontact.drivers.live import SensorGroup

    s = two_sensors
    sims = [
        tcp_sim(profile="generic-float32", signal=constant_signal(s["ft"][n]))
        for n in ("base_ft", "tool_ft")
    ]
    group = SensorGroup(
        [
            ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port, name=n)
            for sim, n in zip(sims, ("base_ft", "tool_ft"), strict=True)
        ]
    )
    group.open()
    est = OnnxEstimator(str(s["path"]), {"positions": s["pos"], "active": [1, 1]}, robot=s["model"])
    records = _run_loop(group, s["q"], est, 5)
    for r in records:
        assert len(r["ft"]) == 12  # both readings, the graph's sensor order
        e = r["estimate"]
        assert e["status"] == 0 and len(e["rank"]) == 2
        np.testing.assert_allclose(e["force"][0], FORCE, atol=2e-3)
        np.testing.assert_allclose(e["force"][1], TOOL_WRENCH[:3], atol=2e-3)
        np.testing.assert_allclose(e["moment"][1], TOOL_WRENCH[3:], atol=2e-3)


def test_run_cli_several_sensors_and_residual(two_sensors, tcp_sim, tmp_path, capsys):
    from export_scenes import correction_checkpoint

    from torchcontact.export import export_residual_checkpoint

    s = two_sensors
    model = s["model"]
    # a correction stack of the tool reading that is the constant [0, 0, 1 N, 0, 0, 0] and reads
    # the extra column temperature
    ckpt = correction_checkpoint(
        tmp_path / "ck", model, "tool_ft", "mlp", constant=[0, 0, 1, 0, 0, 0]
    )
    export_residual_checkpoint(ckpt, tmp_path / "res.onnx", model)
    offset = np.array([0.0, 0, 1, 0, 0, 0])
    sims = {
        n: tcp_sim(
            profile="generic-float32",
            signal=constant_signal(s["ft"][n] + (offset if n == "tool_ft" else 0)),
        )
        for n in ("base_ft", "tool_ft")
    }
    spec = tmp_path / "contacts.json"
    contacts = [  # the contact-spec format: the hand's force and the tool's wrench
        {"link": "hand_skin", "kind": "force", "position": s["pos"][0].tolist()},
        {"link": "tool", "kind": "wrench", "position": s["pos"][1].tolist()},
    ]
    spec.write_text(json.dumps({"contact": contacts}))
    port = _free_udp_port()
    stop = threading.Event()
    sender = threading.Thread(target=_sender, args=(s["q"], port, stop), daemon=True)
    sender.start()
    try:
        rc = main(
            [
                "run",
                "--profile",
                "generic-float32",
                "--tcp",
                f"127.0.0.1:{sims['base_ft'].port}",
                "--source",
                f"tool_ft=tcp://127.0.0.1:{sims['tool_ft'].port}",
                "--onnx",
                str(s["path"]),
                "--contacts",
                str(spec),
                "--robot",
                "tcarm",
                "--residual",
                str(tmp_path / "res.onnx"),
                "--extra",
                "temperature=31.5",
                "--joints",
                f"udp://127.0.0.1:{port}",
                "--require-joints",
                "--duration",
                "1.0",
            ]
        )
    finally:
        stop.set()
        sender.join()
    assert rc == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(lines) > 3
    for r in lines:  # the correction removed the 1 N the tool sensor adds
        np.testing.assert_allclose(r["estimate"]["force"][1], TOOL_WRENCH[:3], atol=2e-3)
        np.testing.assert_allclose(r["estimate"]["force"][0], FORCE, atol=2e-3)
    # a sensor of the graph without a source: one clear error
    assert (
        main(
            [
                "run",
                "--tcp",
                f"127.0.0.1:{sims['base_ft'].port}",
                "--profile",
                "generic-float32",
                "--onnx",
                str(s["path"]),
            ]
        )
        == 2  # a usage error
    )
    assert "missing ['tool_ft']" in capsys.readouterr().err


def test_run_refuses_another_robot(scene, tcp_sim, tmp_path, capsys):
    urdf = tmp_path / "pendulum.urdf"
    urdf.write_text(tc.robots.pendulum_urdf())
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(scene["ft"]))
    rc = main(
        [
            "run",
            "--profile",
            "generic-float32",
            "--tcp",
            f"127.0.0.1:{sim.port}",
            "--onnx",
            str(scene["path"]),
            "--robot",
            str(urdf),
            "--duration",
            "2",
        ]
    )
    io = capsys.readouterr()
    assert rc == 1 and io.out == ""
    assert io.err.count("error:") == 1 and "exported for robot 'tcarm'" in io.err


def test_wrong_joint_count_stops_the_loop(scene, tcp_sim, capsys):
    """Joint states of another robot: one error, the loop stops instead of failing every frame."""
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(scene["ft"]))
    port = _free_udp_port()
    stop = threading.Event()
    sender = threading.Thread(target=_sender, args=(np.zeros(3), port, stop), daemon=True)
    sender.start()
    t0 = time.monotonic()
    try:
        rc = main(
            [
                "run",
                "--profile",
                "generic-float32",
                "--tcp",
                f"127.0.0.1:{sim.port}",
                "--onnx",
                str(scene["path"]),
                "--joints",
                f"udp://127.0.0.1:{port}",
                "--require-joints",
                "--duration",
                "10",
            ]
        )
    finally:
        stop.set()
        sender.join()
    io = capsys.readouterr()
    assert rc == 1 and time.monotonic() - t0 < 5.0
    assert io.out == "" and "joint state has 3 joints, the graph expects 7" in io.err
