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


def test_loop_publishes_forces_and_joint_torques(scene, tcp_sim):
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(scene["ft"]))
    ft = ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port)
    ft.open()
    est = OnnxEstimator(
        str(scene["path"]),
        {"positions": POSITIONS, "active": [0, 1]},
        expect_joint_names=scene["model"].joint_names,
    )
    records = []

    class Keep:
        def publish(self, r):
            records.append(r)

    joints = _joints(scene["q"])
    summary = LiveLoop(ft, joints, est, [Keep()], require_joints=True).run(
        max_frames=10, duration=5.0
    )
    ft.close()
    joints.close()
    assert summary["published"] == 10 and summary["estimator_errors"] == 0
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
            ["run", "--profile", "generic-float32", "--tcp", f"127.0.0.1:{sim.port}",
             "--onnx", str(scene["path"]), "--contacts", str(spec),
             "--joints", f"udp://127.0.0.1:{port}", "--require-joints", "--duration", "1.0"]
        )  # fmt: skip
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
