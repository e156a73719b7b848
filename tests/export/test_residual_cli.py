"""``python -m export residual CHECKPOINT --out FILE.onnx``: a correction stack as one ONNX graph.

The checkpoints are built here with the classes of :mod:`torchcontact.residual` (random layers,
non-identity normalisation so that the graph must carry it) and saved as ``python -m training``
saves them. The graph computes everything from the raw joint state: forward pass, regressor,
features, network.
"""

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

import torchcontact as tc
from export.__main__ import main
from torchcontact.export import RESIDUAL_GRAPH_FORMAT, export_residual_checkpoint
from torchcontact.residual import (
    FeatureSpec,
    ResidualCorrection,
    ResidualGRU,
    ResidualMLP,
    subtree_bodies,
)


def _model(name):
    from robots import load_model

    return tc.RobotModel.from_urdf(tc.robots.tcarm_path()) if name == "tcarm" else load_model(name)


SENSOR = {"tcarm": "base_ft", "icub": "l_arm_ft"}


def _checkpoint(tmp_path, robot, layers, extra=("temperature",)):
    model = _model(robot)
    sensor = SENSOR[robot]
    g = torch.Generator().manual_seed(1)
    kw: dict = {"offset": torch.randn(6, generator=g, dtype=torch.float64)}
    if "inertial" in layers:
        bodies = subtree_bodies(model, sensor)
        kw["inertial_bodies"] = tuple(model.body_names[b] for b in bodies)
        kw["delta"] = 0.05 * torch.randn(10 * len(bodies), generator=g, dtype=torch.float64)
    learned = [x for x in layers if x in ("mlp", "gru")]
    if learned:
        spec = FeatureSpec.default(model, sensor, extra=extra)
        F = len(spec.names(model))
        torch.manual_seed(1)
        net = ResidualMLP(F, 16, 2) if learned[0] == "mlp" else ResidualGRU(F, 8, layers=2)
        net.set_normalisation(torch.randn(64, F) * 2 + 1, torch.randn(64, 6) * 5 - 2)
        kw.update(learned=net, features=spec)
    c = ResidualCorrection(model, sensor, **kw, meta={"data_sha256": "d" * 64})
    return c.save(tmp_path / "-".join(layers)), c


def _inputs(model, n, E, seed=2):
    g = torch.Generator().manual_seed(seed)
    x = [torch.rand(n, model.nv, generator=g, dtype=torch.float64) * 3 - 1.5 for _ in range(3)]
    extra = torch.rand(n, E, generator=g, dtype=torch.float64) * 10 + 25
    return x, extra


@pytest.mark.parametrize(
    "robot,layers",
    [
        ("tcarm", ("offset", "inertial", "mlp")),
        ("icub", ("offset", "inertial", "mlp")),
        ("icub", ("offset", "inertial")),
        ("tcarm", ("offset", "mlp")),
    ],
)
def test_exported_stack_equals_the_torch_correction(tmp_path, robot, layers, capsys):
    ckpt, corr = _checkpoint(tmp_path, robot, layers)
    model = corr.model
    path = tmp_path / "c.onnx"
    urdf = tc.robots.tcarm_path() if robot == "tcarm" else None
    export_residual_checkpoint(ckpt, path, urdf or _icub_path())
    m = onnx.load(str(path))
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in m.graph.initializer)
    E = len(corr.extra_columns)
    names = [i.name for i in m.graph.input]
    assert names == ["q", "qd", "qdd"] + (["extra"] if E else [])
    assert [o.name for o in m.graph.output] == ["correction"]
    props = {p.key: p.value for p in m.metadata_props}
    assert props["format"] == RESIDUAL_GRAPH_FORMAT and props["sensor"] == corr.sensor
    assert json.loads(props["joint_names"]) == list(model.joint_names)
    assert json.loads(props["layers"]) == list(layers)
    assert json.loads(props["extra_columns"]) == corr.extra_columns
    assert props["robot_sha256"] == model.urdf_sha256 and props["data_sha256"] == "d" * 64
    assert props["checkpoint_weights_sha256"] == corr.meta["weights_sha256"]
    assert "N m" in json.loads(props["units"])["correction"] and props["recurrent"] == "false"
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for n in (1, 5, 300):
        (q, qd, qdd), extra = _inputs(model, n, E, seed=n)
        want = corr.correction(q, qd, qdd, dict(zip(corr.extra_columns, extra.T, strict=True)))
        feed = {"q": q, "qd": qd, "qdd": qdd} | ({"extra": extra} if E else {})
        (got,) = sess.run(None, {k: v.float().numpy() for k, v in feed.items()})
        assert got.shape == (n, 6) and got.dtype == np.float32
        # float32 graph vs float64 torch: rounding of the forward pass and the network
        scale = max(1.0, float(want.abs().max()))
        np.testing.assert_allclose(got, want.numpy(), rtol=0, atol=2e-5 * scale)


def _icub_path():
    from robots import icub_path

    return icub_path()


def test_gru_stack_stepped_in_onnx_equals_the_sequence(tmp_path, capsys):
    ckpt, corr = _checkpoint(tmp_path, "tcarm", ("offset", "gru"))
    path = tmp_path / "gru.onnx"
    assert main(["residual", str(ckpt), "--robot", "tcarm", "--out", str(path), "--json"]) == 0
    meta = json.loads(capsys.readouterr().out)  # --json: all the metadata
    assert meta["path"] == str(path) and len(meta["learned_graph"]) > 1000
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["q", "qd", "qdd", "extra", "h_in"]
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert props["recurrent"] == "true" and json.loads(props["state_shape"]) == ["N", 2, 8]
    (q, qd, qdd), extra = _inputs(corr.model, 20, 1)
    want = corr.correction(q, qd, qdd, {"temperature": extra[:, 0]})  # one sequence in time
    h = np.zeros((1, 2, 8), np.float32)  # zero state before the first frame
    for t in range(20):
        feed = {"q": q[t : t + 1], "qd": qd[t : t + 1], "qdd": qdd[t : t + 1]}
        feed["extra"] = extra[t : t + 1]
        r, h = sess.run(None, {k: v.float().numpy() for k, v in feed.items()} | {"h_in": h})
        np.testing.assert_allclose(r[0], want[t].numpy(), atol=2e-4)


def test_export_cli_uses_the_recorded_urdf_and_refuses_tampering(tmp_path, capsys):
    ckpt, corr = _checkpoint(tmp_path, "tcarm", ("offset", "mlp"))
    path = tmp_path / "x.onnx"
    # no URDF recorded and none given: the error says what to pass
    assert main(["residual", str(ckpt), "--out", str(path)]) == 2
    assert "pass the robot's URDF" in capsys.readouterr().err
    meta = json.loads((ckpt / "checkpoint.json").read_text())
    (ckpt / "checkpoint.json").write_text(json.dumps({**meta, "urdf": str(tc.robots.tcarm_path())}))
    assert main(["residual", str(ckpt), "--out", str(path)]) == 0
    out, err = capsys.readouterr()
    # a summary, not the metadata with its base64 graph; no progress on a stderr that is no tty
    lines = out.splitlines()
    assert lines[0].startswith(f"wrote {path} (") and "sensor base_ft of tcarm" in lines[0]
    assert lines[-1] == "  all metadata: --json" and len(out) < 600, out
    assert "checked against torch" in out and "export residual" not in err
    # another robot's URDF is refused
    assert main(["residual", str(ckpt), "--urdf", str(_icub_path()), "--out", str(path)]) == 1
    assert "trained for robot" in capsys.readouterr().err
    w = ckpt / "weights.safetensors"
    data = bytearray(w.read_bytes())
    data[-1] ^= 1
    w.write_bytes(bytes(data))
    path.unlink()
    assert main(["residual", str(ckpt), "--robot", "tcarm", "--out", str(path)]) == 1  # bad data
    assert "does not match" in capsys.readouterr().err
    assert not path.exists()
