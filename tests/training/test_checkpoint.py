import json

import numpy as np
import pytest
import torch

from torchcontact.residual import (
    CheckpointError,
    ResidualCorrection,
    ResidualGRU,
    ResidualMLP,
    feature_names,
    load_residual_model,
    save_residual_model,
)
from training import load_checkpoint
from training.fit import TrainConfig, fit_residual, predict_residual

JOINTS = ["j0", "j1"]


def _meta(extra=()):
    return {
        "features": feature_names(JOINTS, extra),
        "joint_names": JOINTS,
        "sensor": "s",
        "robot_sha256": "abc",
        "data_sha256": "def",
    }


def _toy(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1.5, 1.5, (n, 6))
    y = np.stack(
        [
            np.sin(2 * x[:, 0]),
            np.tanh(3 * x[:, 1]) * x[:, 2],
            x[:, 3] ** 2,
            np.cos(x[:, 0] + x[:, 1]),
            0.5 * x[:, 4],
            3.0 + 0 * x[:, 5],
        ],
        1,
    )
    return x, y


def test_mlp_training_converges_below_threshold():
    x, y = _toy()
    free = np.ones(len(x), bool)
    free[::7] = False  # frames with contacts are never targets
    cfg = TrainConfig(hidden=64, layers=2, epochs=60, lr=1e-2, patience=15, seed=0)
    res = fit_residual(x, y, free, [(0, 2000)], [(2000, 2500)], cfg)
    pred = predict_residual(res.module, x, [(2500, 3000)])[2500:]
    rmse = np.sqrt(((pred - y[2500:]) ** 2).mean())
    assert rmse < 0.08, rmse  # target std ~0.6: the net learned the nonlinear map
    assert res.val_loss[res.best_epoch] < 0.05 * res.val_loss[0]
    # seeded: the same config gives the same weights
    res2 = fit_residual(
        x, y, free, [(0, 2000)], [(2000, 2500)], TrainConfig(**{**vars(cfg), "epochs": 3})
    )
    res3 = fit_residual(
        x, y, free, [(0, 2000)], [(2000, 2500)], TrainConfig(**{**vars(cfg), "epochs": 3})
    )
    for a, b in zip(
        res2.module.state_dict().values(), res3.module.state_dict().values(), strict=True
    ):
        assert torch.equal(a, b)


def test_gru_training_learns_a_state():
    # target is a running (leaky) integral of the input: needs the recurrent state
    rng = np.random.default_rng(1)
    n = 4000
    x = rng.normal(size=(n, 6))
    y = np.zeros((n, 6))
    acc = 0.0
    for i in range(n):
        acc = 0.9 * acc + 0.1 * x[i, 0]
        y[i] = acc
    cfg = TrainConfig(
        kind="gru", hidden=16, layers=1, epochs=25, lr=1e-2, patience=10, seq_len=100, seed=0
    )
    res = fit_residual(x, y, np.ones(n, bool), [(0, 3000)], [(3000, 3500)], cfg)
    pred = predict_residual(res.module, x, [(3500, 4000)])[3500:]
    assert np.sqrt(((pred - y[3500:]) ** 2).mean()) < 0.3 * y.std()


def test_gru_step_by_step_equals_sequence():
    torch.manual_seed(0)
    m = ResidualGRU(6, hidden=8, layers=2).eval()
    x = torch.randn(3, 20, 6, dtype=torch.float64)
    seq, h_seq = m.forward_sequence(x)
    h = None
    for t in range(20):
        r, h = m(x[:, t], h)
        torch.testing.assert_close(r, seq[:, t], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(h, h_seq)
    assert seq.dtype == torch.float64 and h.shape == (3, 2, 8)


@pytest.mark.parametrize("kind", ["mlp", "gru"])
def test_checkpoint_round_trip_bit_exact(tmp_path, kind):
    torch.manual_seed(0)
    m = ResidualMLP(7, hidden=16, layers=2) if kind == "mlp" else ResidualGRU(7, hidden=8)
    m.set_normalisation(torch.randn(50, 7) * 3 + 1, torch.randn(50, 6))
    save_residual_model(tmp_path, m, _meta(["temperature"]))
    for loader in (load_residual_model, load_checkpoint):
        m2, meta = loader(tmp_path, robot_sha256="abc")
        assert meta["features"][-1] == "temperature" and meta["arch"]["kind"] == kind
        s1, s2 = m.state_dict(), m2.state_dict()
        assert s1.keys() == s2.keys()
        for k in s1:
            assert torch.equal(s1[k], s2[k]), k
        x = torch.randn(4, 7, dtype=torch.float64)
        if kind == "mlp":
            assert torch.equal(m(x), m2(x))
        else:
            assert torch.equal(m(x)[0], m2(x)[0])


def _saved(tmp_path):
    m = ResidualMLP(6, hidden=4, layers=1)
    save_residual_model(tmp_path, m, _meta())
    return tmp_path


def test_tampered_weights_refused(tmp_path):
    d = _saved(tmp_path)
    w = d / "weights.safetensors"
    b = bytearray(w.read_bytes())
    b[-3] ^= 0x01  # one bit of one weight
    w.write_bytes(bytes(b))
    with pytest.raises(CheckpointError, match="sha256 .* does not match"):
        load_residual_model(d)


def test_foreign_checkpoint_refused(tmp_path):
    d = _saved(tmp_path)
    meta = json.loads((d / "checkpoint.json").read_text())
    (d / "checkpoint.json").write_text(json.dumps({**meta, "format": "someone-else/2"}))
    with pytest.raises(CheckpointError, match="foreign checkpoint"):
        load_residual_model(d)


def test_wrong_robot_and_inconsistent_structure_refused(tmp_path):
    d = _saved(tmp_path)
    with pytest.raises(CheckpointError, match="trained for robot abc"):
        load_residual_model(d, robot_sha256="other")
    # an arch that does not fit the weights, even with a consistent hash
    meta = json.loads((d / "checkpoint.json").read_text())
    meta["arch"]["hidden"] = 5
    (d / "checkpoint.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="do not fit the recorded arch"):
        load_residual_model(d)
    # a pickle is never loaded: not a safetensors file -> refused before any unpickling
    (d / "weights.safetensors").write_bytes(b"\x80\x04K\x01.")
    with pytest.raises(CheckpointError):
        load_residual_model(d)
    with pytest.raises(CheckpointError, match="missing"):
        load_residual_model(tmp_path / "nowhere")


def test_residual_correction_subtracts_prediction(tmp_path):
    torch.manual_seed(0)
    m = ResidualMLP(7, hidden=8, layers=1)
    save_residual_model(tmp_path, m, _meta(["temperature"]))
    c = ResidualCorrection.load(tmp_path)
    q, qd, qdd = (torch.randn(5, 2, dtype=torch.float64) for _ in range(3))
    temp = torch.linspace(25, 30, 5, dtype=torch.float64)
    x = c.features(q, qd, qdd, {"temperature": temp})
    torch.testing.assert_close(x[:, 2:4], qd)
    torch.testing.assert_close(x[:, -1], temp)
    ft = torch.randn(5, 6, dtype=torch.float64)
    out = c.correct(ft, x)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, ft - m(x).double())
    with pytest.raises(KeyError, match="temperature"):
        c.features(q, qd, qdd)
