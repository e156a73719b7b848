"""The live loop on a step with online inputs (``torchcontact run --c-step / --onnx --online``):
bias tracking, the model's tare, payloads, live identification, causal derivatives, the sender's
contact flag, the bias state in every record (valid JSON) and in the ``--out`` columns.

The simulated Modbus sensor serves the reading the model predicts at a fixed pose, with a tool
and an offset; the loop must find the offset (tracked, or by the model's tare) with the tool
given by ``--payload`` (without it the tool's weight would end in the offset).
"""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest
import torch
from online_scenes import KINDS, LINKS, payload_stream

import torchcontact as tc
from torchcontact.cli import main
from torchcontact.drivers.base import FTSample
from torchcontact.drivers.live import JOINT_CONTACT, JointState, RuntimeEstimator, pack_joint_state
from torchcontact.drivers.simulator import constant_signal

pytest.importorskip("onnxruntime")

OFFSET = np.array([1.2, -0.8, 1.5, 0.05, -0.04, 0.03])  # [N; N m]
TOOL = (0.3, (0.0, 0.0, 0.05))  # kg, m in the hand's frame


@pytest.fixture(scope="module")
def arm():
    torch.set_num_threads(1)
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path())


@pytest.fixture(scope="module")
def files(arm, tmp_path_factory):
    """The arm's C step (the layout of tests/online, its kernel build cached) and ONNX graphs."""
    from torchcontact.export import export_estimator
    from torchcontact.online.cstep import export_c_step

    d = tmp_path_factory.mktemp("live_online")
    export_c_step(arm, None, LINKS, KINDS, d / "arm.so")
    export_estimator(arm, None, LINKS, KINDS, d / "arm.onnx", dtype=torch.float64, online=True)
    export_estimator(arm, None, ["hand_skin"], ["force"], d / "plain.onnx")
    return d


@pytest.fixture(scope="module")
def reading(arm):
    """The pose, and the reading there with the tool and the offset (no contact)."""
    from torchcontact.online.estimator import OnlineEstimator

    q = np.linspace(0.4, -0.5, arm.nv)
    on = OnlineEstimator(arm, None, LINKS, KINDS, backend="eager")
    on.set_payload(TOOL[0], com=TOOL[1])
    z = np.zeros(arm.nv)
    ft_model = on.step(q, z, z, np.zeros((1, 6)), active=np.zeros(3))["ft_model"][0]
    return q, ft_model + OFFSET


def _records(out: str) -> list[dict]:
    """The published records; their bias state is valid JSON (no NaN, no Infinity)."""
    records = [json.loads(line) for line in out.splitlines()]
    for r in records:
        json.dumps(r["estimate"]["bias"], allow_nan=False)
    return records


def _strict(line: str) -> dict:
    """json.loads refusing NaN and Infinity (not JSON)."""

    def refuse(token):
        raise ValueError(f"not JSON: {token}")

    return json.loads(line, parse_constant=refuse)


def _free_udp_port() -> int:
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    return port


def _run(argv, q, port, *, nan_rates=False, flags=0, duration=1.2):
    """``torchcontact run ARGV`` with joint states sent to ``port`` meanwhile (100 Hz)."""
    stop = threading.Event()

    def send():
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rates = np.full_like(q, np.nan if nan_rates else 0.0)
        seq = 0
        while not stop.is_set():
            seq += 1
            tx.sendto(pack_joint_state(seq, time.monotonic_ns(), q, rates, rates, flags),
                      ("127.0.0.1", port))  # fmt: skip
            time.sleep(0.01)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        return main([*argv, "--joints", f"udp://127.0.0.1:{port}", "--require-joints",
                     "--duration", str(duration)])  # fmt: skip
    finally:
        stop.set()
        sender.join()


def test_run_c_step_tracks_the_offset_with_the_tool_and_logs_it(files, reading, tcp_sim,
                                                                tmp_path, capsys):  # fmt: skip
    import pyarrow.parquet as pq

    q, ft = reading
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(ft))
    out = tmp_path / "log.parquet"
    argv = ["run", "--profile", "generic-float32", "--tcp", f"127.0.0.1:{sim.port}",
            "--c-step", str(files / "arm.so"), "--robot", "tcarm", "--track-bias",
            "--bias-time-constant", "0.05", "--payload", f"{TOOL[0]},0,0,0.05,hand",
            "--out", str(out)]  # fmt: skip
    assert _run(argv, q, _free_udp_port()) == 0
    captured = capsys.readouterr()
    records = _records(captured.out)
    assert len(records) > 20
    for r in records:
        b = r["estimate"]["bias"]["base_ft"]
        assert set(b) == {"offset", "std", "since_update", "updated"}
        assert r["estimate"]["status"] == 0 and b["updated"]  # no contact: every frame
    last = records[-1]["estimate"]
    np.testing.assert_allclose(last["bias"]["base_ft"]["offset"], OFFSET, atol=5e-3)
    np.testing.assert_allclose(last["ft_model"][0], ft - OFFSET, atol=5e-3)
    summary = _strict(captured.err.splitlines()[-1])["summary"]
    assert summary["online"]["payloads"]["base_ft"]["mass"] == TOOL[0]
    # the --out log: the readings and every frame's bias state
    t = pq.read_table(out).to_pydict()
    assert {"ft.base_ft", "bias.base_ft", "bias_std.base_ft", "bias_since_update.base_ft",
            "bias_updated.base_ft"} <= set(t)  # fmt: skip
    assert len(t["t_ns"]) >= len(records)
    by_t = dict(zip(t["t_ns"], t["bias.base_ft"], strict=True))
    for r in records:
        np.testing.assert_allclose(by_t[r["t_ns"]], r["estimate"]["bias"]["base_ft"]["offset"])


def test_run_onnx_tare_contact_flag_causal_derivatives(files, reading, tcp_sim, capsys):
    """--onnx (exported with --online): the model's tare once 5 frames are contact-free; the
    sender's contact flag stops the tracking; a sender without rates gets causal ones."""
    q, ft = reading
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(ft))
    base = ["run", "--profile", "generic-float32", "--tcp", f"127.0.0.1:{sim.port}",
            "--onnx", str(files / "arm.onnx"), "--payload", f"{TOOL[0]},0,0,0.05"]  # fmt: skip
    # no tracking, the model's tare after 5 contact-free frames; rates from the filter
    argv = [*base, "--tare", "5", "--derivatives", "causal", "--derivative-window", "7"]
    assert _run(argv, q, _free_udp_port(), nan_rates=True) == 0
    captured = capsys.readouterr()
    records = _records(captured.out)
    status = [r["estimate"]["status"] for r in records]
    assert status[:3] == [2, 2, 2] and status[-1] == 0  # rates NaN until the fit has 4 frames
    tared = [i for i, r in enumerate(records) if "tare" in r["estimate"]]
    assert len(tared) == 1 and tared[0] >= 3 + 4  # 5 valid frames after the filter's warm-up
    np.testing.assert_allclose(records[-1]["estimate"]["bias"]["base_ft"]["offset"], OFFSET,
                               atol=5e-3)  # fmt: skip
    assert not records[-1]["estimate"]["bias"]["base_ft"]["updated"]  # not tracked
    lines = [_strict(x) for x in captured.err.splitlines() if x.startswith("{")]
    der = lines[0]["derivatives"]
    assert der["window"] == 7 and der["delay_frames_qd"] == pytest.approx(0.0, abs=1e-3)
    assert "delay_ms_qdd_1hz" in lines[-1]["summary"]["derivatives"]
    # tracking, but the sender reports a contact: never updated; identification waits
    argv = [*base, "--track-bias", "--identify-payload"]
    assert _run(argv, q, _free_udp_port(), flags=JOINT_CONTACT, duration=0.6) == 0
    captured = capsys.readouterr()
    records = _records(captured.out)
    assert records and all(not r["estimate"]["bias"]["base_ft"]["updated"] for r in records)
    assert records[-1]["estimate"]["bias"]["base_ft"]["since_update"] is None  # never: null
    summary = _strict(captured.err.splitlines()[-1])["summary"]
    assert summary["online"]["identifying"] == ["base_ft"]


def test_identify_payload_live(arm, files):
    """RuntimeEstimator.frame on a simulated stream: the record whose data identify the
    payload carries it, then it is applied (a 0.5 kg tool added mid-stream)."""
    from online_scenes import NOISE

    s = payload_stream(arm, mass=0.5, seconds=12.0, change_s=0.0)
    est = RuntimeEstimator(str(files / "arm.so"), robot="tcarm", track_bias=True,
                           tracker_options={"ft_std": NOISE}, identify="")  # fmt: skip
    found = None
    for i in range(len(s.t)):
        js = JointState(i + 1, int(s.t[i] * 1e9), s.q[i], s.qd[i], s.qdd[i])
        out = est.frame(FTSample(int(s.t[i] * 1e9), i, s.ft[i].reshape(6)), js)
        assert json.dumps(out["bias"], allow_nan=False)
        if "payload_identified" in out:
            found = (s.t[i], out["payload_identified"])
            break
    assert found is not None and found[0] <= 10.0
    assert found[1]["mass"] == pytest.approx(0.5, rel=0.05) and found[1]["link"] == "hand"
    assert est.runtime.online.state.payloads[0].mass == found[1]["mass"]  # applied
    assert est.summary()["events"][0]["payload_identified"] == found[1]


def test_run_online_errors(files, capsys):
    lib, plain = str(files / "arm.so"), str(files / "plain.onnx")
    cases = [
        (["--track-bias"], "--track-bias: only with --onnx or --c-step"),
        (["--onnx", plain, "--track-bias"], "no online inputs"),
        (["--onnx", plain, "--tare", "5"], "no online inputs"),
        (["--c-step", lib, "--payload", "1,0,0"], "MASS,CX,CY,CZ"),
        (["--c-step", lib, "--payload=-1,0,0,0"], "payload mass must be > 0 kg"),
        (["--c-step", lib, "--payload", "1,0,0,0,no_link"], "no_link"),
        (["--c-step", lib, "--ft-std", "1,2"], "--ft-std takes 6 numbers"),
        (["--c-step", lib, "--derivatives", "causal"], "needs joint states"),
        (["--c-step", lib, "--joints", "udp://127.0.0.1:9", "--derivatives", "causal",
          "--derivative-window", "3"], "window must be"),
    ]  # fmt: skip
    for extra, message in cases:
        assert main(["run", "--tcp", "127.0.0.1:1", *extra]) == 2, extra
        err = capsys.readouterr().err
        assert message in err and err.startswith("error:"), (extra, err)
