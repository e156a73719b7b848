"""The estimate command: JSON summaries, several inputs into a folder, one-line data errors (kill -9
then --resume: tests/logs/test_run_faults.py)."""

import json
import os

from torchcontact.cli import main


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
