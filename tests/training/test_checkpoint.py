"""Correction stacks: learned layers, one safetensors checkpoint, loading checks, use."""

import json

import numpy as np
import pytest
import torch

import torchcontact as tc
from torchcontact.residual import (
    CheckpointError,
    FeatureSpec,
    ResidualCorrection,
    ResidualGRU,
    ResidualMLP,
    inertial_params,
    sensor_regressor,
    subtree_bodies,
)
from training.fit import TrainConfig, fit_residual, predict_residual

STACKS = [
    ("offset",),
    ("offset", "inertial"),
    ("offset", "inertial", "mlp"),
    ("mlp",),
    ("offset", "gru"),
]


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
    x[::7] = np.nan  # ... and may be unusable
    cfg = TrainConfig(hidden=64, layers=2, epochs=60, lr=1e-2, patience=15, seed=0)
    res = fit_residual(x, y, free, [(0, 2000)], [(2000, 2500)], cfg)
    pred = predict_residual(res.module, x, [(2500, 3000)])[2500:]
    ok = free[2500:]
    rmse = np.sqrt(((pred[ok] - y[2500:][ok]) ** 2).mean())
    assert rmse < 0.08, rmse  # target std ~0.6: the net learned the nonlinear map
    assert res.val_loss[res.best_epoch] < 0.05 * res.val_loss[0]
    # seeded: the same config gives the same weights
    short = TrainConfig(**{**vars(cfg), "epochs": 3})
    res2 = fit_residual(x, y, free, [(0, 2000)], [(2000, 2500)], short)
    res3 = fit_residual(x, y, free, [(0, 2000)], [(2000, 2500)], short)
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
    assert seq.dtype == torch.float32 and h.shape == (3, 2, 8)


def _stack(arm, layers, seed=0):
    """A correction with random layers (non-identity normalisation, a temperature input)."""
    g = torch.Generator().manual_seed(seed)
    kw: dict = {}
    if "offset" in layers:
        kw["offset"] = torch.randn(6, generator=g, dtype=torch.float64)
    if "inertial" in layers:
        bodies = subtree_bodies(arm, "base_ft")[-2:]
        kw["inertial_bodies"] = tuple(arm.body_names[b] for b in bodies)
        kw["delta"] = 0.05 * torch.randn(20, generator=g, dtype=torch.float64)
    learned = [x for x in layers if x in ("mlp", "gru")]
    if learned:
        spec = FeatureSpec.default(arm, "base_ft", extra=("temperature",))
        F = len(spec.names(arm))
        torch.manual_seed(seed)
        net = ResidualMLP(F, 16, 2) if learned[0] == "mlp" else ResidualGRU(F, 8, layers=2)
        net.set_normalisation(torch.randn(64, F) * 3 + 1, torch.randn(64, 6) * 5 - 2)
        kw.update(learned=net, features=spec)
    return ResidualCorrection(arm, "base_ft", **kw, meta={"data_sha256": "d" * 64})


def _frames(arm, n=40, seed=1):
    g = torch.Generator().manual_seed(seed)
    q, qd, qdd = (torch.rand(n, arm.nv, generator=g, dtype=torch.float64) * 2 - 1 for _ in range(3))
    return q, qd, qdd, {"temperature": torch.linspace(25, 35, n, dtype=torch.float64)}


@pytest.mark.parametrize("layers", STACKS)
def test_checkpoint_round_trip_is_bit_exact(tmp_path, arm, layers):
    c = _stack(arm, layers)
    assert c.layers == list(layers)
    c.save(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.json", "weights.safetensors"]
    c2 = ResidualCorrection.load(tmp_path, arm)
    assert c2.layers == list(layers) and c2.source == str(tmp_path.resolve())
    assert c2.meta["data_sha256"] == "d" * 64
    t1, t2 = c.tensors(), c2.tensors()
    assert t1.keys() == t2.keys()
    for k in t1:
        assert torch.equal(t1[k], t2[k]), k
    args = _frames(arm)
    a, b = c.correction(*args), c2.correction(*args)
    assert torch.equal(a, b) and a.dtype == torch.float64
    assert torch.allclose(a[0], a[1]) == (layers == ("offset",))  # only an offset is constant
    meta = json.loads((tmp_path / "checkpoint.json").read_text())
    assert meta["layers"] == list(layers) and meta["robot_sha256"] == arm.urdf_sha256
    learned = any(x in layers for x in ("mlp", "gru"))
    assert meta["extra_columns"] == (["temperature"] if learned else [])


def test_each_layer_computes_what_it_says(arm):
    """offset + Y delta + network(features), the features being sin/cos, qd, nominal wrench."""
    c = _stack(arm, ("offset", "inertial", "mlp"))
    q, qd, qdd, extra = _frames(arm)
    Y = sensor_regressor(arm, "base_ft", q, qd, qdd)
    bodies = subtree_bodies(arm, "base_ft")
    delta = torch.zeros(len(bodies) * 10, dtype=torch.float64)
    delta[-20:] = c.delta
    nominal = tc.ContactEstimator(arm, ["base_ft"]).predict_ft(
        q, qd, qdd, tc.Contacts((), (), q.new_zeros(len(q), 0, 3))
    )["base_ft"]
    x = torch.cat([torch.stack((q.sin(), q.cos()), -1).flatten(-2), qd, nominal], -1)
    x = torch.cat([x, extra["temperature"][:, None]], -1)
    names = c.features.names(arm)
    assert names[:2] == ["sin.shoulder_yaw", "cos.shoulder_yaw"] and names[-1] == "temperature"
    assert names[2 * arm.nv + arm.nv] == "nominal.fx"
    want = c.offset + Y @ delta + c.learned(x).double()
    torch.testing.assert_close(c.correction(q, qd, qdd, extra), want, rtol=1e-6, atol=1e-5)
    # a single frame, and any batch shape
    torch.testing.assert_close(
        c.correction(q[3], qd[3], qdd[3], {"temperature": extra["temperature"][3]}),
        want[3],
        rtol=1e-6,
        atol=1e-5,
    )
    sh = c.correction(
        *(v.reshape(4, 10, -1) for v in (q, qd, qdd)),
        {"temperature": extra["temperature"].reshape(4, 10)},
    )
    torch.testing.assert_close(sh.reshape(40, 6), want, rtol=1e-6, atol=1e-5)
    # the nominal wrench of the features is the URDF's: Y theta0
    theta0 = torch.as_tensor(inertial_params(arm, bodies))
    torch.testing.assert_close(Y @ theta0, nominal)


def test_correct_subtracts_and_leaves_bad_frames_nan(arm):
    c = _stack(arm, ("offset", "inertial", "mlp"))
    q, qd, qdd, extra = _frames(arm)
    q[5, 2] = float("nan")
    extra["temperature"][7] = float("inf")
    ft = torch.randn(40, 6, dtype=torch.float64)
    out = c.correct(ft, q, qd, qdd, extra)
    corr = c.correction(q, qd, qdd, extra)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, ft - corr, equal_nan=True)
    bad = ~torch.isfinite(out).all(-1)
    assert bad.nonzero().flatten().tolist() == [5, 7]
    with pytest.raises(KeyError, match="temperature"):
        c.correction(q, qd, qdd)


def test_gru_state_carries_over_between_calls(arm):
    c = _stack(arm, ("offset", "gru"))
    assert c.recurrent
    q, qd, qdd, extra = _frames(arm, 30)
    whole = c.correction(q, qd, qdd, extra)
    c.reset()
    parts = [
        c.correction(q[s:e], qd[s:e], qdd[s:e], {"temperature": extra["temperature"][s:e]})
        for s, e in ((0, 7), (7, 8), (8, 30))
    ]
    # float32 network: chunked and whole sequences agree to its rounding
    torch.testing.assert_close(torch.cat(parts), whole, rtol=1e-6, atol=1e-5)
    again = c.correction(q, qd, qdd, extra)  # the state moved on: not a fresh start
    assert not torch.allclose(again, whole)
    c.reset()
    torch.testing.assert_close(c.correction(q, qd, qdd, extra), whole, rtol=1e-6, atol=1e-5)


def _saved(tmp_path, arm, layers=("offset", "inertial", "mlp")):
    return _stack(arm, layers).save(tmp_path)


def test_tampered_weights_refused(tmp_path, arm):
    d = _saved(tmp_path, arm)
    w = d / "weights.safetensors"
    b = bytearray(w.read_bytes())
    b[-3] ^= 0x01  # one bit of one weight
    w.write_bytes(bytes(b))
    with pytest.raises(CheckpointError, match="sha256 .* does not match"):
        ResidualCorrection.load(d, arm)


def test_foreign_and_old_checkpoints_refused(tmp_path, arm):
    d = _saved(tmp_path, arm)
    meta = json.loads((d / "checkpoint.json").read_text())
    for fmt, msg in (
        ("someone-else/2", "foreign checkpoint"),
        ("torchcontact.residual/1", "retrain"),
    ):
        (d / "checkpoint.json").write_text(json.dumps({**meta, "format": fmt}))
        with pytest.raises(CheckpointError, match=msg):
            ResidualCorrection.load(d, arm)
    (d / "checkpoint.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        ResidualCorrection.load(d, arm)


def test_wrong_robot_and_inconsistent_structure_refused(tmp_path, arm):
    from robots import load_model

    d = _saved(tmp_path, arm)
    with pytest.raises(CheckpointError, match="trained for robot .* not this robot"):
        ResidualCorrection.load(d, load_model("icub"))
    good = json.loads((d / "checkpoint.json").read_text())

    def refused(change, match):
        meta = json.loads(json.dumps(good))
        change(meta)
        (d / "checkpoint.json").write_text(json.dumps(meta))
        with pytest.raises(CheckpointError, match=match):
            ResidualCorrection.load(d, arm)

    refused(lambda m: m["learned"]["arch"].update(hidden=5), "do not fit the recorded layers")
    refused(lambda m: m.update(layers=["offset", "mlp"]), "do not fit the recorded layers")
    refused(lambda m: m.update(layers=["offset", "mlp", "gru"]), "bad layer list")
    refused(lambda m: m["inertial"].update(bodies=["nowhere", "hand"]), "not bodies that")
    refused(lambda m: m.update(sensor="wrist_ft"), "does not have")
    refused(lambda m: m["learned"]["features"].update(joints=["elbow_pitch"]), "features")
    refused(lambda m: m["learned"]["features"].update(angles="quaternion"), "bad feature spec")
    (d / "checkpoint.json").write_text(json.dumps(good))
    ResidualCorrection.load(d, arm)  # the untouched checkpoint still loads
    # a pickle is never loaded: not a safetensors file -> refused before any unpickling
    (d / "weights.safetensors").write_bytes(b"\x80\x04K\x01.")
    with pytest.raises(CheckpointError):
        ResidualCorrection.load(d, arm)
    with pytest.raises(CheckpointError, match="missing"):
        ResidualCorrection.load(tmp_path / "nowhere", arm)


def test_checkpoint_keyed_by_the_parsed_robot(tmp_path, arm):
    """A comment or re-indentation of the URDF keeps a checkpoint; a 10 g mass change voids it,
    naming what differs; a checkpoint of an earlier version (text hash only) still loads."""
    import io
    import re

    d = _saved(tmp_path, arm)
    text = open(tc.robots.tcarm_path()).read()
    same = text.replace("<robot", "<!-- a comment -->\n<robot", 1).replace("  ", "\t")
    model = tc.RobotModel.from_urdf(io.StringIO(same))
    assert model.urdf_sha256 != arm.urdf_sha256
    ResidualCorrection.load(d, model)
    m = re.search(r'<link name="hand">.*?<mass value="([0-9.]+)"', text, re.S)
    heavier = text[: m.start(1)] + f"{float(m.group(1)) + 0.01:g}" + text[m.end(1) :]
    with pytest.raises(
        CheckpointError, match=r"not this robot .*: link hand: mass 0\.6 vs 0\.61 kg"
    ):
        ResidualCorrection.load(d, tc.RobotModel.from_urdf(io.StringIO(heavier)))
    meta = json.loads((d / "checkpoint.json").read_text())
    del meta["robot_identity"], meta["robot_identity_sha256"]  # as written before identities
    (d / "checkpoint.json").write_text(json.dumps(meta))
    ResidualCorrection.load(d, arm)
    with pytest.raises(CheckpointError, match="not this robot"):
        ResidualCorrection.load(d, model)  # only the text hash to go by
