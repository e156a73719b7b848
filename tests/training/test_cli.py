import json

from torchcontact.residual import ResidualCorrection
from training.__main__ import main


def test_train_command_writes_a_loadable_checkpoint(tmp_path, arm):
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        """
[data]
frames = 1500
block_seconds = 1.0
extra = ["temperature"]
[data.effects]
offset = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
[model]
kind = "mlp"
hidden = 16
layers = 1
[train]
epochs = 3
"""
    )
    out = tmp_path / "ckpt"
    assert main(["train", "--config", str(cfg), "--out", str(out)]) == 0
    meta = json.loads((out / "checkpoint.json").read_text())
    assert meta["robot_sha256"] == arm.urdf_sha256 and meta["sensor"] == "base_ft"
    assert meta["joint_names"] == list(arm.joint_names) and len(meta["data_sha256"]) == 64
    assert "force_rmse" in meta["metrics"]["d_mlp"]
    assert (out / "loss.png").stat().st_size > 0 and (out / "residual.png").stat().st_size > 0
    c = ResidualCorrection.load(out, robot_sha256=arm.urdf_sha256)
    assert c.feature_names[-1] == "temperature"
