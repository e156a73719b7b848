"""``python -m training``: train on a log in the documented format, benchmark any robot."""

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

import torchcontact as tc
from torchcontact.cli import main as tc_main
from torchcontact.logs import write_simulated_log
from torchcontact.residual import ResidualCorrection
from torchcontact.simulation import UnmodeledEffects
from training.__main__ import main
from training.pipeline import load_config

FX = UnmodeledEffects(
    offset=(1.0, -2.0, 0.5, 0.1, 0.0, 0.0), noise_std=(0.05,) * 6, payload_mass=0.3
)


def _as_other_system_writes_it(path):
    """Joints in another order, vectors as plain lists."""
    t = pq.read_table(path)
    names = json.loads(t.schema.metadata[b"torchcontact.joint_names"])
    order = names[::-1]
    perm = [names.index(j) for j in order]
    for col in ("q", "qd", "qdd"):
        x = np.stack(t.column(col).to_numpy(zero_copy_only=False))[:, perm]
        t = t.set_column(t.column_names.index(col), col, pa.array(x.tolist()))
    meta = {**t.schema.metadata, b"torchcontact.joint_names": json.dumps(order).encode()}
    pq.write_table(t.replace_schema_metadata(meta), path)
    return path


def test_train_on_a_log_in_the_documented_format(tmp_path, arm, capsys):
    log = write_simulated_log(arm, 4000, tmp_path / "run.parquet", seed=7, effects=FX)
    _as_other_system_writes_it(log)
    cfg = tmp_path / "c.toml"
    cfg.write_text("[data]\nblock_seconds = 4.0\n[model]\nhidden = 16\n[train]\nepochs = 4\n")
    out = tmp_path / "ckpt"
    args = ["train", "--config", str(cfg), "--log", str(log), "--robot", "tcarm", "--folds", "3"]
    assert main([*args, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    meta = json.loads((out / "checkpoint.json").read_text())
    assert meta["robot_sha256"] == arm.urdf_sha256 and meta["sensor"] == "base_ft"
    assert meta["urdf"] == str(tc.robots.tcarm_path().resolve())
    assert len(meta["data_sha256"]) == 64 and meta["data"]["files"][0]["frames"] == 4000
    # the payload is re-identified: the inertial layer is in the chosen stack
    assert meta["layers"][:2] == ["offset", "inertial"] and meta["inertial"]["rank"] > 0
    # the report on a log without ground truth: numbers for every method, every axis
    rep = json.loads((out / "report.json").read_text())["report"]
    assert rep["folds"] == 3 and len(rep["chosen_per_fold"]) == 3
    for method in ("none", "offset", "offset+inertial", "offset+mlp", "stack"):
        row = rep["metrics"][method]
        assert all(np.isfinite(row[f"rms.{a}"]) for a in ("fx", "fy", "fz", "mx", "my", "mz"))
        assert row["frames_free"] == meta["data"]["targets"]  # every contact-free frame scored
    m = rep["metrics"]
    assert m["stack"]["residual_force_rms"] < 0.5 * m["offset"]["residual_force_rms"]
    assert "| held out | chosen stack |" in (out / "report.md").read_text() and "chosen" in printed
    # a learned layer records its features' training range, and the report says how to cover it
    learned = meta["layers"][-1] in ("mlp", "gru")
    assert ("feature_ranges" in meta) == learned
    assert ("## Training range" in (out / "report.md").read_text()) == learned
    assert (out / "loss.png").stat().st_size > 0 and (out / "residual.png").stat().st_size > 0
    c = ResidualCorrection.load(out, arm)
    assert c.layers == meta["layers"]
    # the checkpoint is applied by estimate, joints matched by name there too
    est = tmp_path / "est.parquet"
    assert (
        tc_main(["estimate", str(log), "--out", str(est), "--residual", str(out), "--quiet"]) == 0
    )
    assert pq.read_table(est).num_rows == 4000


def test_train_refuses_bad_input_with_one_line(tmp_path, arm, capsys):
    log = write_simulated_log(arm, 300, tmp_path / "run.parquet", seed=7)
    assert main(["train", "--log", str(log), "--sensor", "nope", "--out", str(tmp_path / "o")]) == 2
    assert "no F/T sensor 'nope'" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[data]\nframes = 10\n[modle]\nkind = 'mlp'\n")
    assert main(["train", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "unknown tables ['modle']" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_example_config_is_valid():
    cfg, raw = load_config(Path(__file__).parents[2] / "training" / "configs" / "example.toml")
    assert cfg.data.robot == "tcarm" and cfg.stack.layers == "auto" and cfg.features.nominal
    assert cfg.train.hidden == 64 and raw["data"]["effects"]["cable_force"] == 3.0


@pytest.mark.parametrize("robot,sensor", [("icub", "l_arm_ft")])
def test_benchmark_runs_on_any_robot(tmp_path, robot, sensor, capsys):
    out = tmp_path / "bench"
    args = ["benchmark", "--robot", robot, "--sensor", sensor, "--conditions", "payload"]
    args += ["--frames", "3000", "--folds", "2", "--block-seconds", "3", "--epochs", "3"]
    torch.manual_seed(0)
    assert main([*args, "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["robot"] == "iCub" and res["sensor"] == sensor
    rows = res["results"]["payload"]
    # the payload on the hand is re-identified to the noise floor (the oracle)
    assert rows["stack"]["force_rmse"] < 1.5 * rows["oracle"]["force_rmse"]
    assert rows["offset"]["force_rmse"] > 3 * rows["oracle"]["force_rmse"]
    assert "payload: stack/oracle" in capsys.readouterr().out


def test_heldout_scores_frames_never_trained_on(tmp_path, capsys):
    base = ["heldout", "--robot", "tcarm", "--conditions", "payload", "--epochs", "2"]
    base += ["--train-frames", "3000", "--test-frames", "1000"]
    results = {}
    for flag in ([], ["--new-session"]):
        out = tmp_path / ("new" if flag else "next")
        assert main([*base, *flag, "--out", str(out)]) == 0
        results[bool(flag)] = json.loads((out / "heldout.json").read_text())["results"]["payload"]
    capsys.readouterr()
    for rows in results.values():
        assert rows["stack"]["force_rmse"] < 1.5 * rows["oracle"]["force_rmse"]
        assert rows["offset"]["force_rmse"] > 3 * rows["oracle"]["force_rmse"]
    # another session is other test frames
    assert results[True]["none"]["force_rmse"] != results[False]["none"]["force_rmse"]
