"""``python -m export residual CHECKPOINT --out FILE.onnx``: residual checkpoints to ONNX.

The checkpoints are built here with the classes of :mod:`torchcontact.residual` (random weights,
non-identity normalisation so that the graph must carry it) and saved with
``save_residual_model``, as ``python -m training`` does.
"""

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from export.__main__ import main
from torchcontact.export import check_parity
from torchcontact.residual import (
    ResidualGRU,
    ResidualMLP,
    feature_names,
    load_residual_model,
    save_residual_model,
)

JOINTS = ["shoulder", "elbow", "wrist"]
FEATURES = feature_names(JOINTS, ["temperature"])
F = len(FEATURES)


def _checkpoint(tmp_path, kind):
    torch.manual_seed(1)
    m = ResidualMLP(F, hidden=16, layers=2) if kind == "mlp" else ResidualGRU(F, 8, layers=2)
    m.set_normalisation(torch.randn(64, F) * 3 + 1, torch.randn(64, 6) * 5 - 2)
    meta = {
        "features": FEATURES,
        "joint_names": JOINTS,
        "sensor": "base_ft",
        "robot_sha256": "a" * 64,
        "data_sha256": "d" * 64,
    }
    return save_residual_model(tmp_path / kind, m, meta)


@pytest.mark.parametrize("kind", ["mlp", "gru"])
def test_export_residual_cli_parity_and_metadata(tmp_path, kind, capsys):
    ckpt = _checkpoint(tmp_path, kind)
    path = tmp_path / f"{kind}.onnx"
    assert main(["residual", str(ckpt), "--out", str(path)]) == 0
    assert json.loads(capsys.readouterr().out)["path"] == str(path)
    module, meta = load_residual_model(ckpt)

    m = onnx.load(str(path))
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in m.graph.initializer)
    assert [o.version for o in m.opset_import if o.domain in ("", "ai.onnx")] == [18]
    props = {p.key: p.value for p in m.metadata_props}
    assert json.loads(props["feature_names"]) == FEATURES
    assert json.loads(props["joint_names"]) == JOINTS
    assert props["sensor"] == "base_ft" and props["data_sha256"] == "d" * 64
    assert props["kind"] == kind and props["recurrent"] == str(kind == "gru").lower()
    assert props["checkpoint_weights_sha256"] == meta["weights_sha256"]
    assert "N m" in json.loads(props["units"])["residual"] and props["model_version"]
    inputs = [i.name for i in m.graph.input]
    assert inputs == (["features", "h_in"] if kind == "gru" else ["features"])

    # onnxruntime vs torch, float32, dynamic batch
    gen = torch.Generator().manual_seed(2)
    graph = module if kind == "mlp" else (lambda x, h: module(x, h))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for n in (1, 2, 7, 1024):
        x = torch.randn(n, F, generator=gen) * 3 + 1
        if kind == "mlp":
            assert check_parity(module, path, x, atol=1e-5) <= 1e-5
            continue
        h = torch.randn(n, 2, 8, generator=gen)
        with torch.no_grad():
            r_ref, h_ref = graph(x, h)
        r, h_out = sess.run(None, {"features": x.numpy(), "h_in": h.numpy()})
        assert r.dtype == np.float32 and r.shape == (n, 6) and h_out.shape == (n, 2, 8)
        assert np.abs(r - r_ref.numpy()).max() <= 1e-5
        assert np.abs(h_out - h_ref.numpy()).max() <= 1e-5


def test_gru_stepped_in_onnx_equals_the_sequence(tmp_path, capsys):
    ckpt = _checkpoint(tmp_path, "gru")
    path = tmp_path / "gru.onnx"
    assert main(["residual", str(ckpt), "--out", str(path), "--no-check"]) == 0
    module, _ = load_residual_model(ckpt)
    x = torch.randn(3, 20, F, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        ref, _ = module.forward_sequence(x)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    h = np.zeros((3, 2, 8), np.float32)  # zero state before the first frame
    for t in range(20):
        r, h = sess.run(None, {"features": x[:, t].numpy(), "h_in": h})
        assert np.abs(r - ref[:, t].numpy()).max() <= 1e-5


def test_tampered_checkpoint_is_refused(tmp_path, capsys):
    ckpt = _checkpoint(tmp_path, "mlp")
    w = ckpt / "weights.safetensors"
    data = bytearray(w.read_bytes())
    data[-1] ^= 1
    w.write_bytes(bytes(data))
    assert main(["residual", str(ckpt), "--out", str(tmp_path / "x.onnx")]) == 1  # bad data
    assert "does not match" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()
