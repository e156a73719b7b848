"""``torchcontact estimate --residual``: a learned F/T correction applied before estimation.

The residual models are built here, not trained: a :class:`ResidualMLP` whose last layer has zero
weights and a bias equal to a known sensor offset predicts exactly that offset (the default
normalisation is the identity), so a simulated log with that offset is estimated exactly with the
correction and wrongly without it. The offset values are float32-exact.
"""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from torchcontact.cli import main
from torchcontact.logs import LogError, estimate_file, write_simulated_log
from torchcontact.logs.format import META_RESIDUAL
from torchcontact.residual import (
    ResidualGRU,
    ResidualMLP,
    feature_names,
    save_residual_model,
)
from torchcontact.simulation import UnmodeledEffects

OFFSET = [2.5, -1.25, 4.0, 0.125, -0.25, 0.5]  # [N; N m], exact in float32


def _meta(model, *, robot_sha256=None, sensor="base_ft"):
    joints = list(model.joint_names)
    return {
        "features": feature_names(joints, ["temperature"]),
        "joint_names": joints,
        "sensor": sensor,
        "robot_sha256": robot_sha256 or model.urdf_sha256,
        "data_sha256": "0" * 64,
    }


def _offset_mlp(model, directory, **meta_kwargs):
    meta = _meta(model, **meta_kwargs)
    m = ResidualMLP(len(meta["features"]), hidden=8, layers=1)
    with torch.no_grad():
        m.net[-1].weight.zero_()
        m.net[-1].bias.copy_(torch.tensor(OFFSET))
    return save_residual_model(directory, m, meta)


@pytest.fixture(scope="module")
def offset_log(model, tmp_path_factory):
    path = tmp_path_factory.mktemp("offset") / "log.parquet"
    return write_simulated_log(model, 400, path, seed=3, effects=UnmodeledEffects(offset=OFFSET))


def _single_contact_errors(path):
    rows = pq.read_table(path).column("contacts").to_pylist()
    errs = [
        np.abs(np.subtract(r[0]["force"], r[0]["true_force"])).max() for r in rows if len(r) == 1
    ]
    assert len(errs) > 20
    return np.asarray(errs)


def test_residual_cli_recovers_forces_that_the_offset_spoils(model, offset_log, tmp_path, capsys):
    ckpt = _offset_mlp(model, tmp_path / "ckpt")
    with_res, without = tmp_path / "with.parquet", tmp_path / "without.parquet"
    args = ["estimate", str(offset_log), "--quiet", "--batch-size", "64"]
    assert main([*args, "--out", str(with_res), "--residual", str(ckpt)]) == 0
    assert main([*args, "--out", str(without)]) == 0
    capsys.readouterr()
    assert _single_contact_errors(with_res).max() < 1e-8
    assert _single_contact_errors(without).min() > 0.1
    meta = pq.read_schema(with_res).metadata
    rec = json.loads(meta[META_RESIDUAL])
    weights = json.loads((ckpt / "checkpoint.json").read_text())["weights_sha256"]
    assert rec == {
        "checkpoint": str(ckpt.resolve()),
        "weights_sha256": weights,
        "sensor": "base_ft",
        "kind": "mlp",
    }
    assert META_RESIDUAL not in pq.read_schema(without).metadata


def test_foreign_robot_checkpoint_is_refused(model, offset_log, tmp_path, capsys):
    ckpt = _offset_mlp(model, tmp_path / "ckpt", robot_sha256="f" * 64)
    out = tmp_path / "o.parquet"
    assert main(["estimate", str(offset_log), "--out", str(out), "--residual", str(ckpt)]) == 1
    err = capsys.readouterr().err
    assert "trained for robot ffff" in err and model.urdf_sha256 in err
    assert not out.exists() and not out.with_name("o.parquet.partial").exists()


def test_missing_feature_column_and_unknown_sensor_are_named(model, tmp_path):
    ckpt = _offset_mlp(model, tmp_path / "ckpt")
    no_temp = write_simulated_log(model, 50, tmp_path / "nt.parquet", seed=1, temperature=False)
    with pytest.raises(LogError, match="needs column 'temperature', which the log lacks"):
        estimate_file(no_temp, model, tmp_path / "o.parquet", residual=ckpt)
    other = _offset_mlp(model, tmp_path / "other", sensor="wrist_ft")
    with pytest.raises(LogError, match="corrects sensor 'wrist_ft'"):
        estimate_file(no_temp, model, tmp_path / "o2.parquet", residual=other)


def _gru_ckpt(model, directory):
    meta = _meta(model)
    torch.manual_seed(0)
    m = ResidualGRU(len(meta["features"]), hidden=8)
    return save_residual_model(directory, m, meta)


def test_gru_state_carries_across_chunks_and_resume_is_refused(model, offset_log, tmp_path):
    ckpt = _gru_ckpt(model, tmp_path / "gru")
    one = estimate_file(
        offset_log, model, tmp_path / "one.parquet", batch_size=10_000, residual=ckpt
    )
    many = estimate_file(offset_log, model, tmp_path / "many.parquet", batch_size=37, residual=ckpt)
    a = np.stack(pq.read_table(one["output"])["joint_torques"].to_numpy(zero_copy_only=False))
    b = np.stack(pq.read_table(many["output"])["joint_torques"].to_numpy(zero_copy_only=False))
    # a chunked run equals one sequence: the state was not reset between chunks (float32 GRU)
    np.testing.assert_allclose(a, b, atol=1e-5)
    plain = estimate_file(offset_log, model, tmp_path / "plain.parquet")
    c = np.stack(pq.read_table(plain["output"])["joint_torques"].to_numpy(zero_copy_only=False))
    assert np.abs(a - c).max() > 1e-3  # the correction did change the estimates
    with pytest.raises(LogError, match="not supported with a recurrent"):
        estimate_file(offset_log, model, tmp_path / "r.parquet", residual=ckpt, resume=True)
