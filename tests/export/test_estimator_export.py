"""The exported estimator graphs against the torch estimator: every output, both graphs, dtypes.

``export_estimator`` writes a batched graph (the estimator program, one node per scalar
operation) and a single-frame graph (vectorised over bodies and slots). Both must compute
``ContactEstimator.estimate`` -- forces, moments, joint torques, rank, unknowns, residual,
status, covariance -- to ``PARITY`` (export_scenes), in float64 and float32, on four layouts: one and
two sensors, every slot kind, moving base, torque rows, covariance, prismatic and mimic joints, a
pruned iCub arm.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from export_scenes import (
    LAYOUTS,
    assert_parity,
    reference,
    reference_estimator,
    robot_model,
    scene,
)

import torchcontact as tc
from torchcontact.errors import InputError

STEP_INPUTS = (
    "positions",
    "active",
    "directions",
    "wrenches",
    "ft_residual",
    "omega",
    "domega",
    "proper_acc",
    "tau_measured",
    "tau_mask",
    "ft_cov",
)


def _kwargs(x: dict, i: int | None = None) -> dict:
    pick = (lambda v: v) if i is None else (lambda v: v[i])
    return {k: pick(x[k]) for k in STEP_INPUTS if k in x}


def _only_torques(ref, rt):
    """The reference with NaN for the joints whose torques the graph does not output."""
    if ref is None:
        return None
    keep = [rt.joint_names.index(j) for j in rt.metadata["torque_joints"]]
    tau = ref.joint_torques.clone()
    drop = [c for c in range(rt.nv) if c not in keep]
    tau[:, drop] = float("nan")
    return ref._replace(joint_torques=tau)


def _step_all(rt, x: dict) -> dict:
    """``rt.step`` over every frame, stacked like ``rt.run``'s outputs."""
    outs = [
        rt.step(x["q"][i], x["qd"][i], x["qdd"][i], x["ft"][i], **_kwargs(x, i))
        for i in range(len(x["q"]))
    ]
    return {k: np.stack([np.asarray(o[k]) for o in outs]) for k in outs[0]}


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("name", ["tcarm", "tcarm2", "panda", "icub"])
def test_graphs_match_torch_estimator(exports, name, dtype):
    x = scene(name, 24, seed=1)
    ref = reference(name, x, dtype)
    ref32 = reference(name, x, dtype, compute=np.float32) if dtype == np.float32 else None
    sensors = reference_estimator(name, dtype).sensor_names
    rt = exports.runtime(name, dtype)
    assert rt.step_session is not None
    ref, ref32 = (_only_torques(r, rt) for r in (ref, ref32))
    # frames differ and the rank-deficient ones are there (two pure forces in one region)
    assert not np.allclose(ref.force[0], ref.force[1])
    assert_parity(_step_all(rt, x), ref, sensors, dtype, ref32=ref32)
    out = rt.run(x["q"], x["qd"], x["qdd"], x["ft"], **_kwargs(x))
    assert_parity(out, ref, sensors, dtype, ref32=ref32)


def test_estimates_recover_the_true_contacts(exports):
    """The round trip: readings simulated from known forces are explained by the estimate."""
    x = scene("tcarm", 16, seed=3, noise=0.0)
    rt = exports.runtime("tcarm")
    out = rt.run(x["q"], x["qd"], x["qdd"], x["ft"], **_kwargs(x))
    ident = (out["rank"] == out["unknowns"]).all(-1) & (x["active"].sum(-1) > 0)
    assert ident.sum() >= 8
    truth = x["truth"][..., :3] * x["active"][..., None]
    np.testing.assert_allclose(out["force"][ident], truth[ident], atol=1e-9)


@pytest.mark.parametrize("graph", ["step", "batched"])
def test_status_bits_and_nan_frames(tmp_path, graph):
    """Bad frames get the torch estimator's status and NaN outputs; the other frames are exact."""
    from torchcontact.export import export_estimator
    from torchcontact.runtime import EstimatorRuntime

    lay = LAYOUTS["tcarm2"]
    model = robot_model("tcarm2")
    limits = dict(velocity_margin=1.5, ft_range={"base_ft": [300, 300, 300, 60, 60, 60]})
    path = tmp_path / "limits.onnx"
    export_estimator(
        model,
        None,
        lay["links"],
        lay["kinds"],
        path,
        dtype=torch.float64,
        moving_base=True,
        covariance=True,
        **limits,
    )
    rt = EstimatorRuntime(path, step_graph=graph == "step")
    x = scene("tcarm2", 20, seed=4, patterns=[(1, 1, 1, 1)])
    nan, inf = float("nan"), float("inf")
    for key, idx, v in [
        ("ft", (1, 0, 2), nan),
        ("ft_residual", (2, 1, 4), inf),
        ("q", (3, 1), nan),
        ("omega", (4, 0), inf),
        ("positions", (5, 0, 1), nan),
        ("directions", (6, 1, 0), nan),
        ("wrenches", (7, 3, 3), nan),
        ("positions", (8, 1, 1), nan),
        ("qd", (10, 3), 4.0),
        ("ft", (11, 0, 3), 80.0),
        ("qd", (12, 3), 4.0),
        ("q", (12, 0), nan),
        ("directions", (14, 1), 0.0),
        ("directions", (16, 1), 0.0),
    ]:
        x[key][idx] = v
    x["active"][8, 1] = 0.0  # an inactive slot's NaN position is no error
    x["active"][16, 1] = 0.0  # nor an inactive slot's zero-length direction
    est = tc.ContactEstimator(model, None, **limits)
    ref = reference("tcarm2", x, estimator=est)
    assert set(ref.status.tolist()) >= {0, 1, 2, 4, 8, 64}
    out = (
        _step_all(rt, x)
        if graph == "step"
        else rt.run(x["q"], x["qd"], x["qdd"], x["ft"], **_kwargs(x))
    )
    assert_parity(out, ref, est.sensor_names, np.float64)
    # a bad frame's rank is 0, as the estimator's (it computes on zeros)
    assert (np.asarray(out["rank"])[ref.status.numpy() > 0] == 0).all()


def test_overflow_sets_bit_32(exports):
    rt = exports.runtime("tcarm")
    x = scene("tcarm", 2, seed=5)
    x["qd"][1, 2] = 1e200  # finite input, overflowing products
    out = rt.run(x["q"], x["qd"], x["qdd"], x["ft"], **_kwargs(x))
    one = rt.step(x["q"][1], x["qd"][1], x["qdd"][1], x["ft"][1], **_kwargs(x, 1))
    ref = reference("tcarm", x)
    assert ref.status.tolist() == [0, 32] and out["status"].tolist() == [0, 32]
    assert one["status"] == 32 and np.isnan(one["force"]).all()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_graphs_load_and_use_no_linear_algebra(exports, dtype):
    """float64 and float32 graphs load in onnxruntime; only elementwise, gather and matrix ops
    (and the solve's ``If``, whose branches are held to the same list)."""
    path = exports.path("panda", dtype)
    step = path.with_name(path.name.replace(".onnx", ".step.onnx"))
    allowed = {
        "Add",
        "Sub",
        "Mul",
        "Div",
        "Neg",
        "Sqrt",
        "Sin",
        "Cos",
        "Pow",
        "Where",
        "Greater",
        "Equal",
        "And",
        "Or",
        "Not",
        "IsNaN",
        "Abs",
        "Min",
        "Max",
        "Gather",
        "GatherElements",
        "MatMul",
        "Gemm",
        "Concat",
        "Split",
        "Squeeze",
        "Reshape",
        "Slice",
        "Transpose",
        "Cast",
        "Shape",
        "Expand",
        "Identity",
        "ArgMax",
        "ReduceMax",
        "ReduceSum",
        "ReduceSumSquare",
        "ReduceL2",
        "ReduceMin",
        "If",
    }

    def ops(graph) -> set[str]:
        out = set()
        for n in graph.node:
            out.add(n.op_type)
            for a in n.attribute:
                if a.type == onnx.AttributeProto.GRAPH:
                    out |= ops(a.g)
        return out

    for p in (path, step):
        m = onnx.load(str(p))
        onnx.checker.check_model(m)
        assert ops(m.graph) <= allowed, ops(m.graph) - allowed
        ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])


def test_single_frame_graph_is_vectorised(exports):
    """Its node count does not grow with the number of bodies (tcarm 9, iCub 39 bodies)."""
    sizes = {}
    for name in ("tcarm", "icub"):
        p = exports.path(name)
        sizes[name] = len(
            onnx.load(str(p.with_name(p.name.replace(".onnx", ".step.onnx")))).graph.node
        )
    assert sizes["tcarm"] <= 260 and sizes["icub"] <= 300, sizes
    p = exports.path("tcarm")
    assert len(onnx.load(str(p)).graph.node) > 10 * sizes["tcarm"]  # the batched graph


def test_metadata(exports):
    p = exports.path("panda")
    meta = {q.key: q.value for q in onnx.load(str(p)).metadata_props}
    step = {
        q.key: q.value
        for q in onnx.load(str(p.with_name(p.name.replace(".onnx", ".step.onnx")))).metadata_props
    }
    model = robot_model("panda")
    assert meta["format"] == "torchcontact.estimator/2" and meta["graph"] == "batched"
    assert step["graph"] == "step" and {**step, "graph": "batched"} == meta
    assert meta["urdf_sha256"] == model.urdf_sha256 and meta["robot"] == model.name
    assert json.loads(meta["joint_names"]) == list(model.joint_names)
    assert [s["name"] for s in json.loads(meta["sensors"])] == ["wrist_ft"]
    assert json.loads(meta["slot_kinds"]) == list(LAYOUTS["panda"]["kinds"])
    assert json.loads(meta["moving_base"]) and json.loads(meta["torque_rows"])
    assert json.loads(meta["covariance"]) and meta["dtype"] == "float64"
    lay = json.loads(meta["step_inputs"])
    assert lay["q"] == [0, [model.nv]] and "tau_mask" in lay and "ft_cov" in lay
    assert "covariance" in json.loads(meta["step_outputs"])
    assert json.loads(meta["torque_joints"]) == list(model.joint_names)
    icub = {q.key: q.value for q in onnx.load(str(exports.path("icub"))).metadata_props}
    assert json.loads(icub["torque_joints"]) == [
        "l_shoulder_pitch",
        "l_shoulder_roll",
        "l_shoulder_yaw",
        "l_elbow",
        "l_wrist_prosup",
        "l_wrist_pitch",
        "l_wrist_yaw",
    ]


def test_layout_errors_name_the_problem(tmp_path):
    from torchcontact.export import export_estimator

    model = robot_model("tcarm")
    with pytest.raises(InputError, match="unknown kind"):
        export_estimator(model, None, ["hand_skin"], ["push"], tmp_path / "a.onnx")
    with pytest.raises(ValueError, match="unknown F/T sensors"):
        export_estimator(model, ["wrist_ft"], ["hand_skin"], ["force"], tmp_path / "a.onnx")
    with pytest.raises(ValueError, match="unknown link"):
        export_estimator(model, None, ["hand_skn"], ["force"], tmp_path / "a.onnx")
    with pytest.raises(ValueError, match="unknown joints"):
        export_estimator(
            model, None, ["hand_skin"], ["force"], tmp_path / "a.onnx", joints=["elbow"]
        )
    assert not (tmp_path / "a.onnx").exists()


def test_cli_exports(tmp_path):
    path = tmp_path / "tcarm.onnx"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "export",
            "estimator",
            "--robot",
            "tcarm",
            "--slot",
            "hand_skin:force",
            "--slot",
            "forearm_skin:force_dir",
            "--dtype",
            "float64",
            "--moving-base",
            "--torque-rows",
            "--covariance",
            "--joints",
            "sensed",
            "--out",
            str(path),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    printed = json.loads(r.stdout)
    meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    # without --json: a few lines, not the kilobytes of metadata
    from export.__main__ import estimator_summary

    summary = estimator_summary(str(path), printed["step_path"], meta)
    lines = summary.splitlines()
    assert len(lines) == 6 and len(summary) < 1000 and len(r.stdout) > 5 * len(summary)
    assert "slots hand_skin:force, forearm_skin:force_dir" in lines[1]
    assert "float64" in lines[4] and "moving base" in lines[4] and "covariance" in lines[4]
    assert printed["path"] == str(path) and printed["step_path"].endswith(".step.onnx")
    assert meta["robot"] == "tcarm" and meta["dtype"] == "float64"
    assert json.loads(meta["slot_links"]) == ["hand_skin", "forearm_skin"]
    assert json.loads(meta["moving_base"]) and json.loads(meta["covariance"])
    assert path.with_name("tcarm.step.onnx").is_file()
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "export",
            "estimator",
            "--robot",
            "tcarm",
            "--slot",
            "hand_skin:push",
            "--out",
            str(tmp_path / "b.onnx"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "unknown kind" in bad.stderr
