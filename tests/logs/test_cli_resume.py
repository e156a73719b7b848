import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from torchcontact.cli import main

ROOT = Path(__file__).resolve().parents[2]


def test_estimate_cli_json_and_folder_output(sim_log, sim_log_q_only, tmp_path, capsys):
    assert main(["estimate", str(sim_log), "--out", str(tmp_path / "one.parquet"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 600 and summary["sensors"] == ["base_ft"]
    folder = tmp_path / "many"
    folder.mkdir()
    (tmp_path / "in").mkdir()
    os.symlink(sim_log, tmp_path / "in" / "a.parquet")
    os.symlink(sim_log_q_only, tmp_path / "in" / "b.parquet")
    args = ["estimate", str(tmp_path / "in" / "*.parquet"), "--out", str(folder), "--json"]
    assert main([*args, "--sensor", "base_ft", "--device", "cpu", "--batch-size", "256"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["derived"] for s in out] == [[], ["qd", "qdd"]]
    assert sorted(p.name for p in folder.iterdir()) == ["a.parquet", "b.parquet"]


def test_estimate_cli_errors_name_the_file(tmp_path, capsys):
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"not parquet at all")
    assert main(["estimate", str(bad), "--out", str(tmp_path / "o.parquet")]) == 1
    assert "bad.parquet: not a readable Parquet file" in capsys.readouterr().err
    assert main(["estimate", str(tmp_path / "nope*.parquet"), "--out", "x"]) == 1


def test_sigkill_then_resume_equals_uninterrupted(model, tmp_path):
    from torchcontact.logs import estimate_file, write_simulated_log

    log = write_simulated_log(model, 4000, tmp_path / "long.parquet", seed=5, derivatives=False)
    out = tmp_path / "out.parquet"
    sidecar = tmp_path / "out.parquet.progress.json"
    cmd = [sys.executable, "-m", "torchcontact.cli", "estimate", str(log), "--out", str(out)]
    cmd += ["--batch-size", "100", "--quiet", "--device", "cpu"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    done = 0
    while time.monotonic() < deadline and proc.poll() is None:
        if sidecar.exists():
            try:
                done = json.loads(sidecar.read_text())["parts_done"]
            except (ValueError, KeyError):
                done = 0
            if done >= 2:
                break
        time.sleep(0.02)
    if proc.poll() is not None:
        pytest.fail(f"run ended before it could be killed: {proc.communicate()}")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    # nothing that looks complete
    assert not out.exists()
    assert (tmp_path / "out.parquet.partial").is_dir()
    # without --resume: refused, the parts stay
    res = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert res.returncode == 1 and "--resume" in res.stderr
    res = subprocess.run([*cmd, "--resume", "--json"], env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["resumed_chunks"] >= 2 and summary["processed_now"] < 4000
    assert not (tmp_path / "out.parquet.partial").exists() and not sidecar.exists()
    ref = estimate_file(log, model, tmp_path / "ref.parquet", batch_size=100)
    a, b = pq.read_table(out), pq.read_table(ref["output"])
    assert a.num_rows == 4000
    assert a["t_ns"].to_pylist() == b["t_ns"].to_pylist()  # none missing or duplicated
    assert a.equals(b)  # same chunking: bit-identical rows
