"""The live loop: UDP joint states in, estimator, JSON lines out over UDP loopback."""

import io
import json
import socket
import time

import numpy as np
import pytest

from torchcontact.cli import main
from torchcontact.drivers import ModbusFTSensor
from torchcontact.drivers.live import (
    JsonLinesPublisher,
    LiveLoop,
    UdpJointSource,
    UdpPublisher,
    load_estimator,
    pack_joint_state,
    unpack_joint_state,
)
from torchcontact.drivers.simulator import constant_signal

WRENCH = [1.5, -2.25, 100.0, 0.125, -0.5, 3.0]


def toy_estimator(q, qd, qdd, ft):
    return {"sum_q": float(np.sum(q)), "n": len(q), "fz": ft[2], "vec": qd * 2}


def test_packet_layout_bytes():
    p = pack_joint_state(1, 2, [1.0], [2.0], [3.0])
    assert p.hex() == (
        "54434a53"
        "0100"
        "0000"
        "0100000000000000"
        "0200000000000000"
        "01000000"
        "000000000000f03f"
        "0000000000000040"
        "0000000000000840"
    )
    js = unpack_joint_state(p)
    assert (js.seq, js.t_ns, js.q.tolist(), js.qd.tolist(), js.qdd.tolist()) == (
        1,
        2,
        [1],
        [2],
        [3],
    )


@pytest.mark.parametrize(
    ("packet", "message"),
    [
        (b"TCJS", "shorter than its header"),
        (b"XXXX" + pack_joint_state(1, 2, [1.0], [2.0], [3.0])[4:], "magic"),
        (pack_joint_state(1, 2, [1.0], [2.0], [3.0])[:-1], "expected 52"),
        (pack_joint_state(1, 2, [1.0], [2.0], [3.0])[:4] + b"\x02\x00" + b"\x00" * 46, "version 2"),
    ],
)
def test_bad_packets(packet, message):
    with pytest.raises(ValueError, match=message):
        unpack_joint_state(packet)


def test_udp_joint_source_keeps_newest_and_rejects_stale():
    src = UdpJointSource()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for seq in (5, 3, 7):
        tx.sendto(pack_joint_state(seq, 0, [seq], [0], [0]), src.address)
    tx.sendto(b"garbage", src.address)
    time.sleep(0.05)
    assert src().seq == 7
    assert (src.received, src.stale, src.rejected) == (2, 1, 1)
    src.close()


def test_loop_publishes_json_lines_over_udp(tcp_sim):
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(WRENCH))
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(1.0)
    joints = UdpJointSource()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.sendto(pack_joint_state(42, 0, [0.1, 0.2, 0.3], [1, 2, 3], [0, 0, 0]), joints.address)
    time.sleep(0.05)
    ft = ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port)
    ft.open()
    stdout = io.StringIO()
    loop = LiveLoop(
        ft, joints, toy_estimator, [UdpPublisher(*rx.getsockname()), JsonLinesPublisher(stdout)]
    )
    summary = loop.run(max_frames=20, duration=5.0)
    ft.close()
    records = [json.loads(rx.recv(65536)) for _ in range(20)]
    assert records == [json.loads(line) for line in stdout.getvalue().splitlines()]
    assert [r["seq"] for r in records] == list(range(20))
    for r in records:
        assert r["joint_seq"] == 42
        assert r["estimate"] == {"sum_q": pytest.approx(0.6), "n": 3, "fz": 100.0, "vec": [2, 4, 6]}
        np.testing.assert_allclose(r["ft"], WRENCH)
        assert 0 < r["latency_us"] < 1e6
    assert summary["published"] == 20
    assert 0 < summary["latency_p50_us"] <= summary["latency_p99_us"]


def test_loop_requires_joints_and_survives_estimator_errors(tcp_sim):
    sim = tcp_sim(profile="generic-float32")
    ft = ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port)
    ft.open()
    out = io.StringIO()
    skipped = LiveLoop(
        ft, lambda: None, toy_estimator, [JsonLinesPublisher(out)], require_joints=True
    )
    skipped.run(duration=0.2)
    assert skipped.published == 0 and skipped.skipped_no_joints > 0

    def broken(q, qd, qdd, ft):
        raise RuntimeError("boom")

    loop = LiveLoop(ft, None, broken, [JsonLinesPublisher(out)])
    loop.run(max_frames=3, duration=2.0)
    ft.close()
    assert loop.estimator_errors == 3
    assert json.loads(out.getvalue().splitlines()[-1])["estimate"] == {
        "error": "RuntimeError: boom"
    }


def test_publisher_is_loopback_only():
    with pytest.raises(ValueError, match="loopback only"):
        UdpPublisher("192.168.1.10", 9000)


def test_load_estimator_errors():
    with pytest.raises(ValueError, match="module:function"):
        load_estimator("nocolon")
    with pytest.raises(ValueError, match="cannot import"):
        load_estimator("no_such_module_xyz:f")
    with pytest.raises(ValueError, match="no callable 'nope'"):
        load_estimator("torchcontact.drivers.live:nope")


def test_run_cli_udp(tcp_sim, tmp_path):
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(WRENCH))
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(1.0)
    out = tmp_path / "run.parquet"
    rc = main(
        [
            "run",
            "--profile",
            "generic-float32",
            "--tcp",
            f"127.0.0.1:{sim.port}",
            "--publish",
            f"udp://127.0.0.1:{rx.getsockname()[1]}",
            "--duration",
            "0.5",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    record = json.loads(rx.recv(65536))
    assert record["estimate"]["force_norm"] == pytest.approx(np.linalg.norm(WRENCH[:3]))
    assert out.exists()
