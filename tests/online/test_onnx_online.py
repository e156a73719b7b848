"""Offsets and payloads on the ONNX step (export_estimator(online=...)): the step graph's online
stage against the torch estimator in float64, a correction stack's layers as the online inputs'
defaults, the commands and their refusals, the one robot check of graphs and C libraries."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from online_scenes import KINDS, LINKS

import torchcontact as tc
from torchcontact.errors import InputError, ModelMismatchError
from torchcontact.online.estimator import OnlineEstimator
from torchcontact.residual import sensor_regressor
from torchcontact.runtime import EstimatorRuntime

TOL = dict(rtol=0.0, atol=1e-12)
#: after the solve: the step graph solves by Gauss-Jordan, torch by pivoted Cholesky (same
#: pivots), so the estimates agree to the conditioning of G times 1e-16 (tests/export)
SOLVED = dict(rtol=1e-10, atol=1e-10)


def _frames(rng, nv, K, n):
    """Random frames; every other one contact-free (the offsets update on those)."""
    for k in range(n):
        q, qd, qdd = rng.uniform(-1.5, 1.5, (3, nv))
        yield {"q": q, "qd": qd, "qdd": qdd, "ft": rng.normal(0, 10, (1, 6)),
               "positions": rng.uniform(-0.03, 0.03, (K, 3)),
               "active": (rng.random(K) < 0.6).astype(float) * (k % 2)}  # fmt: skip


def test_online_step_graph_equals_the_torch_estimator_float64(arm, arm_onnx):
    """Tracked offsets and a payload with an inertia: every output, ft_model, the regressor."""
    rt = EstimatorRuntime(arm_onnx, robot="tcarm", track_bias=True)
    t = OnlineEstimator(arm, None, LINKS, KINDS, track_bias=True, backend="eager")
    meta = rt.metadata
    assert meta["online"][0]["payload_link"] == "hand" and meta["slot_regions"] == [0, 0, 0]
    for r in (rt, t):
        r.set_payload(0.7, com=(0.01, 0.02, 0.05), inertia=np.diag([0.01, 0.012, 0.015]))
    rng = np.random.default_rng(0)
    updated = []
    for k, f in enumerate(_frames(rng, arm.nv, len(LINKS), 10)):
        a = rt.step(f, t=0.01 * k)
        b = t.step(f["q"], f["qd"], f["qdd"], f["ft"], f["positions"], f["active"], t=0.01 * k)
        assert a["status"] == b["status"] == 0
        np.testing.assert_allclose(a["ft_model"], b["ft_model"], **TOL)
        for key in ("force", "moment", "joint_torques", "residual"):
            np.testing.assert_allclose(a[key], b[key], **SOLVED, err_msg=key)
        np.testing.assert_allclose(a["bias"].offset, b["bias"].offset, **TOL)
        assert a["bias"].updated.tolist() == b["bias"].updated.tolist()
        updated.append(bool(a["bias"].updated[0]))
    assert updated == [True, False] * 5  # contact-free frames only
    q, qd, qdd = (torch.as_tensor(f[k])[None] for k in ("q", "qd", "qdd"))
    Y = sensor_regressor(arm, "base_ft", q, qd, qdd, [arm.frame("hand").body])[0].numpy()
    np.testing.assert_allclose(rt.backend.output("regressor.base_ft"), Y, **TOL)
    # a bad frame: NaN outputs, no update
    out = rt.step({**f, "q": np.full(7, np.nan)})
    assert out["status"] == 2 and np.isnan(out["ft_model"]).all()
    assert not out["bias"].updated.any()


def test_a_stack_s_offset_and_inertial_layers_are_the_online_defaults(arm, tmp_path):
    """Offset + inertial + MLP stack chained into an online graph: offset -> bias, inertial ->
    theta (exactly), the learned layer stays in the graph and in ft_model (float32 network)."""
    from torchcontact.export import export_estimator, export_residual_checkpoint
    from torchcontact.residual import FeatureSpec, ResidualCorrection, ResidualMLP, subtree_bodies

    spec = FeatureSpec.default(arm, "base_ft")
    torch.manual_seed(2)
    net = ResidualMLP(len(spec.names(arm)), 8, 1)
    net.set_normalisation(torch.randn(32, len(spec.names(arm))), torch.randn(32, 6))
    bodies = [arm.body_names[b] for b in subtree_bodies(arm, "base_ft")][-2:]
    g = torch.Generator().manual_seed(4)
    stack = ResidualCorrection(
        arm, "base_ft", offset=torch.randn(6, dtype=torch.float64, generator=g),
        inertial_bodies=bodies, delta=0.05 * torch.randn(20, dtype=torch.float64, generator=g),
        learned=net, features=spec,
    ).save(tmp_path / "ckpt")  # fmt: skip
    export_residual_checkpoint(stack, tmp_path / "stack.onnx", arm)
    path = tmp_path / "arm.onnx"
    export_estimator(arm, None, LINKS, KINDS, path, dtype=torch.float64, online=True,
                     residual=[tmp_path / "stack.onnx"])  # fmt: skip
    rt = EstimatorRuntime(path, robot=arm)
    t = OnlineEstimator(arm, None, LINKS, KINDS, correction=stack, backend="eager")
    np.testing.assert_array_equal(rt.online.state.bias(), t.state.bias())
    np.testing.assert_array_equal(rt.online.state.theta(0), t.state.theta(0))
    assert np.abs(t.state.theta(0)).max() > 0 and np.abs(t.state.bias()).max() > 0
    rng = np.random.default_rng(1)
    for f in _frames(rng, arm.nv, len(LINKS), 4):
        a = rt.step(f)
        b = t.step(f["q"], f["qd"], f["qdd"], f["ft"], f["positions"], f["active"])
        np.testing.assert_allclose(a["ft_model"], b["ft_model"], rtol=0, atol=2e-5)
        np.testing.assert_allclose(a["force"], b["force"], rtol=0, atol=2e-5)
    # the learned layer's part of ft_model is not negligible (the comparison above sees it)
    q, qd, qdd = (torch.as_tensor(f[k])[None] for k in ("q", "qd", "qdd"))
    learned = ResidualCorrection(arm, "base_ft", learned=net, features=spec).correction(q, qd, qdd)
    assert learned.abs().max() > 0.05


def test_commands_and_refusals_on_the_onnx_step(arm_onnx, tmp_path):
    rt = EstimatorRuntime(arm_onnx, robot="tcarm")
    q = np.full(7, 0.3)
    with pytest.raises(InputError, match="needs a frame first"):
        rt.tare()
    frame = {"q": q, "qd": q * 0, "qdd": q * 0, "ft": np.ones((1, 6))}
    rt.step({**frame, "active": [0.0, 1.0, 0.0]})
    with pytest.raises(InputError, match="contact is active on sensor.*base_ft"):
        rt.tare()
    out = rt.step({**frame, "active": np.zeros(3)})
    s = rt.tare()
    np.testing.assert_allclose(s.offset[0], 1.0 - out["ft_model"][0], **TOL)
    after = rt.step({**frame, "active": np.zeros(3)})
    np.testing.assert_allclose(after["residual"], 0.0, atol=1e-9)  # re-zeroed: nothing left
    with pytest.raises(InputError, match="triangle inequality"):
        rt.set_payload(1.0, inertia=np.diag([1.0, 0.1, 0.1]))
    with pytest.raises(InputError, match="positive definite"):
        rt.set_payload(1.0, inertia=np.diag([-1.0, 0.1, 0.1]))
    with pytest.raises(InputError, match="not carried by sensor"):
        rt.set_payload(1.0, link="no_such_link")
    with pytest.raises(InputError, match="start_identification"):
        rt.identify_payload()
    before = rt.step({**frame, "active": np.zeros(3)})["ft_model"]
    rt.set_payload(0.5, com=(0, 0, 0.1))
    heavier = rt.step({**frame, "active": np.zeros(3)})["ft_model"]
    assert abs(np.linalg.norm(heavier[0, :3] - before[0, :3]) - 0.5 * 9.81) < 1e-9
    # a graph without the online stage: its step is today's, and it says what it lacks
    from torchcontact.export import export_estimator

    plain = tmp_path / "plain.onnx"
    export_estimator(tc.RobotModel.from_urdf(tc.robots.tcarm_path()), None, ["hand_skin"],
                     ["force"], plain, dtype=torch.float64)  # fmt: skip
    with pytest.raises(InputError, match="no online inputs.*--online"):
        EstimatorRuntime(plain, track_bias=True)
    p = EstimatorRuntime(plain)
    assert "bias" not in p.step({"q": q, "qd": q, "qdd": q, "ft": np.zeros(6)})
    with pytest.raises(InputError, match="no online inputs"):
        p.tare()
    names = set(p.metadata["step_inputs"]) | set(p.metadata["step_outputs"])
    assert not names & {"bias", "ft_model"} and not any(n.startswith("theta.") for n in names)


def test_one_robot_check_for_graphs_and_c_libraries(arm_lib, tmp_path):
    """The C library records the robot's identity as the graphs do: a reformatted URDF fits, a
    10 g mass change is refused and named; a library of round 1 (the URDF text's hash only) is
    accepted when the text matches."""
    from torchcontact.onnx.checks import check_file

    path, meta = arm_lib
    assert meta["robot_identity_sha256"] == tc.RobotModel.from_urdf(
        tc.robots.tcarm_path()).identity.sha256  # fmt: skip
    text = Path(tc.robots.tcarm_path()).read_text()
    same = tmp_path / "reformatted.urdf"
    same.write_text(text.replace("<robot", "<!-- kept -->\n<robot", 1).replace("  ", "    "))
    EstimatorRuntime(path, robot=same)
    m = re.search(r'<link name="hand">.*?<mass value="([0-9.]+)"', text, re.S)
    heavier = tmp_path / "heavier.urdf"
    heavier.write_text(text[: m.start(1)] + f"{float(m.group(1)) + 0.01:g}" + text[m.end(1) :])
    with pytest.raises(ModelMismatchError, match=r"link hand: mass \S+ vs \S+ kg"):
        EstimatorRuntime(path, robot=heavier)
    EstimatorRuntime(path, expect_robot_sha256=meta["robot_identity_sha256"])
    old = {k: v for k, v in meta.items() if not k.startswith("robot_identity")}
    check_file(str(path), old, robot="tcarm")
    with pytest.raises(ModelMismatchError, match="URDF sha256"):
        check_file(str(path), old, robot=same)
    # the duplicate check of round 1 is gone: one place decides
    assert not (Path(tc.__file__).parent / "online" / "cruntime.py").exists()


def test_cli_online(tmp_path, capsys):
    from export.__main__ import main

    out = tmp_path / "arm.onnx"
    argv = ["estimator", "--robot", "tcarm", "--slot", "hand_skin:force", "--dtype", "float64",
            "--online", "--payload-link", "base_ft=tool", "--out", str(out)]  # fmt: skip
    assert main([*argv, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert json.loads(printed["online"])[0]["payload_link"] == "tool"
    rt = EstimatorRuntime(out, robot="tcarm", track_bias=True)
    assert rt.online.state.sensors[0].payload_link == "tool"
    assert (
        main(argv[:7] + ["--payload-link", "base_ft=tool", "--out", str(tmp_path / "b.onnx")]) == 2
    )
    assert "--payload-link goes with --online" in capsys.readouterr().err


def test_c_step_with_the_learned_layer_as_an_onnx_graph_beside_it(arm, arm_lib, tmp_path):
    """EstimatorRuntime(lib, backend="c", residual=learned.onnx): the library holds the physics,
    onnxruntime the network; the offsets learn from ft - (ft_model + the network's part)."""
    from torchcontact.export import export_residual_checkpoint
    from torchcontact.residual import FeatureSpec, ResidualCorrection, ResidualMLP

    spec = FeatureSpec.default(arm, "base_ft", nominal=False)
    torch.manual_seed(5)
    net = ResidualMLP(len(spec.names(arm)), 16, 2)
    net.set_normalisation(torch.randn(32, len(spec.names(arm))), torch.randn(32, 6))
    ck = ResidualCorrection(arm, "base_ft", learned=net, features=spec).save(tmp_path / "ck")
    export_residual_checkpoint(ck, tmp_path / "learned.onnx", arm)
    rt = EstimatorRuntime(arm_lib[0], robot="tcarm", residual=tmp_path / "learned.onnx",
                          track_bias=True)  # fmt: skip
    t = OnlineEstimator(arm, None, LINKS, KINDS, correction=ck, track_bias=True, backend="eager")
    for f in _frames(np.random.default_rng(2), arm.nv, len(LINKS), 4):
        a = rt.step(f)
        b = t.step(f["q"], f["qd"], f["qdd"], f["ft"], f["positions"], f["active"])
        for key in ("force", "ft_model"):  # the network runs in float32
            np.testing.assert_allclose(a[key], b[key], rtol=0, atol=1e-5, err_msg=key)
        np.testing.assert_allclose(a["bias"].offset, b["bias"].offset, rtol=0, atol=1e-5)
