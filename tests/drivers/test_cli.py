"""The ``torchcontact sensor`` and ``run`` commands against the simulator."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.cli import main
from torchcontact.drivers.log import read_ft_log

ROOT = Path(__file__).parents[2]


@pytest.fixture
def simulate(tmp_path):
    procs = []

    def start(*args):
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        cmd = [sys.executable, "-m", "torchcontact.cli", "sensor", "simulate", *args]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
        procs.append(proc)
        line = proc.stdout.readline()  # "serving <profile> on pty|tcp <where>"
        assert line.startswith("serving"), line
        return proc, line.split()[-1]

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(5)


def test_sensor_read_stream_writes_parquet(simulate, tmp_path, capsys):
    proc, port = simulate("--pty", "--link", str(tmp_path / "ft.pty"), "--streaming-at-start")
    out = tmp_path / "log.parquet"
    rc = main(["sensor", "read", "--port", port, "--stream", "--duration", "1", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert '"firmware": "V1.0.4"' in text and "Hz" in text
    summary = json.loads(text.strip().splitlines()[-1])
    table = pq.read_table(out)
    assert table.schema.field("t_ns").type == pa.int64()
    assert table.schema.field("ft.robotiq_ft300").type == pa.list_(pa.float64(), 6)
    assert table.num_rows == summary["log"]["rows"] == summary["stats"]["frames"]
    assert 80 <= table.num_rows <= 130
    t, w = read_ft_log(out, "robotiq_ft300")
    assert np.all(np.diff(t) > 0) and w.shape == (table.num_rows, 6)
    assert np.all(np.abs(w[:, 2] - 15.0) <= 20.0 + 1e-9)  # the simulator's Fz sinusoid
    proc.send_signal(signal.SIGTERM)
    stats = json.loads(proc.stdout.read().strip().splitlines()[-1])["simulator"]
    assert stats["stream_stops"] >= 2 and stats["stream_starts"] == 1


def test_sensor_read_tcp_and_replay(simulate, tmp_path, capsys):
    log = tmp_path / "in.parquet"
    from torchcontact.drivers.log import FTLogWriter

    with FTLogWriter(log, "arm") as w:
        for i in range(50):
            w.append(i * 10_000_000, np.full(6, 0.5) * (i % 2))
    proc, where = simulate(
        "--tcp", "127.0.0.1:0", "--profile", "generic-float32", "--replay", str(log)
    )
    out = tmp_path / "out.parquet"
    rc = main(
        [
            "sensor",
            "read",
            "--profile",
            "generic-float32",
            "--tcp",
            where,
            "--duration",
            "0.5",
            "--out",
            str(out),
            "--sensor",
            "left",
        ]
    )
    assert rc == 0
    _, w = read_ft_log(out, "left")
    assert len(w) > 20
    assert set(np.unique(w)) <= {0.0, 0.5}  # replayed values, exact in float32


def test_errors_are_clear(capsys, tmp_path):
    assert main(["sensor", "read", "--port", str(tmp_path / "ttyUSB7"), "--duration", "0.1"]) == 1
    assert "ttyUSB7" in capsys.readouterr().err
    assert main(["sensor", "read", "--profile", "nope", "--tcp", "127.0.0.1:1502"]) == 1
    assert "unknown profile 'nope'" in capsys.readouterr().err
    assert main(["sensor", "simulate", "--tcp", "10.1.2.3:1502"]) == 2  # a usage error
    assert "error: refusing to serve on 10.1.2.3: loopback only" in capsys.readouterr().err


def test_import_does_not_need_pymodbus():
    code = (
        "import sys, torchcontact, torchcontact.cli, torchcontact.drivers; "
        "print('pymodbus' in sys.modules or 'serial' in sys.modules)"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert res.stdout.strip() == "False", res.stderr


def _strict_json(line):
    """Parse as a strict parser does (JavaScript, Go, serde, jq): no NaN or Infinity."""

    def reject(token):
        raise ValueError(f"not JSON: {token}")

    return json.loads(line, parse_constant=reject)


def test_run_publishes_strict_json_with_null_for_nan(tcp_sim, tmp_path, capsys, monkeypatch):
    """Torques a ``--joints sensed`` graph does not compute are NaN: published as null."""
    (tmp_path / "nan_estimator.py").write_text(
        "import numpy as np\n"
        "def estimate(q, qd, qdd, ft):\n"
        "    return {'joint_torques': np.array([1.5, np.nan, -np.inf]), 'gain': float('nan')}\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    sim = tcp_sim(profile="generic-float32")  # in this process: no interpreter to start
    args = ["run", "--profile", "generic-float32", "--tcp", f"127.0.0.1:{sim.port}"]
    args += ["--duration", "0.5"]
    assert main([*args, "--estimator", "nan_estimator:estimate"]) == 0
    out, err = capsys.readouterr()
    lines = [_strict_json(x) for x in out.splitlines()]
    assert len(lines) > 3
    for r in lines:
        assert r["estimate"] == {"joint_torques": [1.5, None, None], "gain": None}
    assert _strict_json(err.strip().splitlines()[-1])["summary"]["published"] == len(lines)
