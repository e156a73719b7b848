"""The whole estimator as one ONNX graph: parity with the torch estimator, metadata, CLI."""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from export_scenes import robot_model, scene

import torchcontact as tc

# float32 graph vs float64 torch eigh: forces to 1e-4 N on identifiable frames (issue 6)
FORCE_ATOL_F32 = 1e-4


@functools.cache
def _session(path: str) -> ort.InferenceSession:
    # building a session optimises the ~8k-node graph (seconds): once per file
    return ort.InferenceSession(path, providers=["CPUExecutionProvider"])


def _run(path, x):
    s = _session(str(path))
    feed = {k: v.numpy().astype(np.float32) for k, v in x.items()}
    return dict(zip([o.name for o in s.get_outputs()], s.run(None, feed), strict=True))


@pytest.mark.parametrize("robot", ["tcarm", "icub"])
def test_parity_with_torch_estimator(robot, exported):
    model, est, links, kinds, x, truth = scene(robot, 256, seed=2)
    ft = {s: x["ft"][:, i] for i, s in enumerate(est.sensor_names)}
    c = tc.Contacts(links, kinds, x["positions"], x["directions"], x["wrenches"], x["active"] > 0)
    ref = est.estimate(x["q"], x["qd"], x["qdd"], ft, c)
    out = _run(exported[robot], x)
    rank = torch.stack([ref.rank[s] for s in est.sensor_names], -1).numpy()
    unk = torch.stack([ref.unknowns[s] for s in est.sensor_names], -1).numpy()
    np.testing.assert_array_equal(out["rank"], rank)
    np.testing.assert_array_equal(out["unknowns"], unk)
    np.testing.assert_array_equal(out["status"], 0)
    ident = (rank == unk).all(-1)
    assert ident.sum() > 50 and (~ident).sum() > 50
    f = out["force"].astype(np.float64)
    err = np.abs(f[ident] - ref.force.numpy()[ident]).max()
    assert err <= FORCE_ATOL_F32, err
    # the estimate is the truth on identifiable frames (round trip)
    act = x["active"].numpy()[..., None]
    assert np.abs(f[ident] - (truth[..., :3].numpy() * act)[ident]).max() <= FORCE_ATOL_F32
    # rank-deficient frames: the minimum-norm solution, float32 rounding of a pseudo-inverse
    # with a small retained eigenvalue; documented bound 1e-3 N
    assert np.abs(f - ref.force.numpy()).max() <= 1e-3
    m = out["moment"].astype(np.float64)
    assert np.abs(m[ident] - ref.moment.numpy()[ident]).max() <= FORCE_ATOL_F32


def test_ft_residual_is_subtracted_and_status_flags(exported):
    model, est, links, kinds, x, _ = scene("tcarm", 8, seed=3)
    base = _run(exported["tcarm"], x)
    y = dict(x)
    off = torch.zeros_like(x["ft"])
    off[..., 2] = 5.0
    y["ft"], y["ft_residual"] = x["ft"] + off, off
    shifted = _run(exported["tcarm"], y)
    np.testing.assert_allclose(shifted["force"], base["force"], atol=1e-4)
    y["ft_residual"] = torch.zeros_like(off)  # without the correction the estimate moves
    assert np.abs(_run(exported["tcarm"], y)["force"] - base["force"]).max() > 0.1
    bad = dict(x)
    bad["ft"] = x["ft"].clone()
    bad["ft"][3, 0, 1] = float("nan")
    out = _run(exported["tcarm"], bad)
    assert out["status"][3] == 1 and np.isnan(out["force"][3]).all()
    assert (np.delete(out["status"], 3) == 0).all()


def test_dynamic_batch_and_metadata(exported):
    mo = onnx.load(str(exported["icub"]))
    meta = {p.key: p.value for p in mo.metadata_props}
    model = robot_model("icub")
    assert meta["robot"] == model.name and meta["urdf_sha256"] == model.urdf_sha256
    assert json.loads(meta["joint_names"]) == list(model.joint_names)
    assert json.loads(meta["slot_kinds"])[2] == "wrench"
    assert [s["name"] for s in json.loads(meta["sensors"])][:2] == ["l_leg_ft", "r_leg_ft"]
    assert meta["dtype"] == "float32" and meta["opset"].isdigit()
    assert {"torchcontact_version", "units", "joint_names", "slot_links"} <= set(meta)
    ops = {n.op_type for n in mo.graph.node}
    assert not ops & {"Eig", "Svd", "Inverse"}  # nothing outside the standard domain
    for i in mo.graph.input:
        assert i.type.tensor_type.shape.dim[0].dim_param == "N"
    _, _, _, _, x, _ = scene("icub", 7, seed=4)
    for n in (1, 2, 7):
        out = _run(exported["icub"], {k: v[:n] for k, v in x.items()})
        assert out["force"].shape == (n, 5, 3) and out["rank"].shape == (n, 6)


def test_cli_exports(tmp_path):
    path = tmp_path / "tcarm.onnx"
    r = subprocess.run(
        [sys.executable, "-m", "export", "estimator", "--robot", "tcarm", "--slot",
         "hand_skin:force", "--dtype", "float64", "--out", str(path)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert meta["robot"] == "tcarm" and meta["dtype"] == "float64"
    assert json.loads(meta["slot_links"]) == ["hand_skin"]
    assert json.loads(meta["sensors"])[0]["name"] == "base_ft"
