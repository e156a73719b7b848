"""torchcontact.runtime: numpy/onnxruntime only, refusals, inputs, chained residual corrections."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import onnx
import pytest
import torch
from export_scenes import LAYOUTS, correction_checkpoint, reference, robot_model, scene

import torchcontact as tc
from torchcontact.errors import InputError, ModelMismatchError


def test_runtime_does_not_import_torch():
    code = "import torchcontact.runtime, sys; assert 'torch' not in sys.modules, 'torch imported'"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def test_step_equals_run_and_loads_lazily(exports):
    from torchcontact.runtime import EstimatorRuntime

    rt = EstimatorRuntime(exports.path("tcarm"), robot="tcarm")
    assert rt._batched is None  # the batched graph loads on the first run()
    x = scene("tcarm", 6, seed=5)
    batch = rt.run(
        x["q"],
        x["qd"],
        x["qdd"],
        x["ft"],
        x["positions"],
        x["active"],
        ft_residual=x["ft_residual"],
    )
    for i in range(6):
        one = rt.step(
            x["q"][i],
            x["qd"][i],
            x["qdd"][i],
            x["ft"][i],
            x["positions"][i],
            x["active"][i],
            ft_residual=x["ft_residual"][i],
        )
        np.testing.assert_allclose(one["force"], batch["force"][i], atol=1e-9)
        np.testing.assert_allclose(one["joint_torques"], batch["joint_torques"][i], atol=1e-9)
        assert one["status"] == batch["status"][i] and one["rank"].dtype == np.int64
    # a dict of readings, 1-D readings for one sensor, step through the batched graph
    d = rt.step(x["q"][0], x["qd"][0], x["qdd"][0], {"base_ft": x["ft"][0, 0]}, x["positions"][0])
    flat = rt.step(x["q"][0], x["qd"][0], x["qdd"][0], x["ft"][0, 0], x["positions"][0])
    np.testing.assert_array_equal(d["force"], flat["force"])
    nostep = EstimatorRuntime(exports.path("tcarm"), step_graph=False)
    assert nostep.step_session is None
    o = nostep.step(x["q"][0], x["qd"][0], x["qdd"][0], x["ft"][0, 0], x["positions"][0])
    np.testing.assert_allclose(o["force"], flat["force"], atol=1e-9)


def test_refuses_another_robot_or_layout(exports, tmp_path):
    from torchcontact.runtime import EstimatorRuntime, robot_identity

    path = exports.path("tcarm")
    model = robot_model("tcarm")
    assert robot_identity("tcarm")[0] == model.urdf_sha256 == robot_identity(model)[0]
    EstimatorRuntime(path, robot=model)
    EstimatorRuntime(path, robot=tc.robots.tcarm_path())
    other = tmp_path / "pendulum.urdf"
    other.write_text(tc.robots.pendulum_urdf())
    with pytest.raises(ModelMismatchError, match="exported for robot 'tcarm'.*not for this robot"):
        EstimatorRuntime(path, robot=other)
    renamed = type("M", (), {"urdf_sha256": model.urdf_sha256, "joint_names": ("a",) * 7})()
    with pytest.raises(ModelMismatchError, match="expects joints"):
        EstimatorRuntime(path, robot=renamed)
    with pytest.raises(ModelMismatchError, match="no such URDF"):
        EstimatorRuntime(path, robot=tmp_path / "missing.urdf")
    with pytest.raises(ModelMismatchError, match="sha256"):
        EstimatorRuntime(path, expect_robot_sha256="0" * 64)
    with pytest.raises(ModelMismatchError, match="expects joints"):
        EstimatorRuntime(path, expect_joint_names=["a"] * 7)
    with pytest.raises(ModelMismatchError, match="expects sensors"):
        EstimatorRuntime(path, expect_sensors=["tool_ft"])
    with pytest.raises(ModelMismatchError, match="slots"):
        EstimatorRuntime(path, expect_slots=(["hand_skin"], ["force"]))
    # a graph of the previous format (one Jacobi graph, no layouts) is refused with the fix
    old = onnx.load(str(path))
    for p in old.metadata_props:
        if p.key == "format":
            p.value = "torchcontact.estimator/1"
    onnx.save(old, str(tmp_path / "old.onnx"))
    with pytest.raises(ModelMismatchError, match="re-export"):
        EstimatorRuntime(tmp_path / "old.onnx")
    with pytest.raises(InputError, match="no such file"):
        EstimatorRuntime(tmp_path / "none.onnx")


def test_input_errors_name_the_input(exports):
    rt = exports.runtime("panda")  # moving base, torque rows, covariance
    x = scene("panda", 1, seed=6)
    kw = {
        k: x[k][0]
        for k in ("omega", "domega", "proper_acc", "tau_measured", "ft_cov", "directions")
    }
    ok = rt.step(x["q"][0], x["qd"][0], x["qdd"][0], x["ft"][0], x["positions"][0], **kw)
    assert ok["covariance"].shape == (3, 6, 6) and ok["status"] == 0
    zero = rt.step(
        x["q"][0],
        x["qd"][0],
        x["qdd"][0],
        x["ft"][0],
        x["positions"][0],
        **{**kw, "directions": None},
    )
    assert zero["status"] == 8  # the active force_dir slot has no direction
    with pytest.raises(InputError, match=r"positions must have shape \(3, 3\)"):
        rt.step(x["q"][0], x["qd"][0], x["qdd"][0], x["ft"][0], np.zeros((2, 3)), **kw)
    with pytest.raises(InputError, match="omega is required"):
        rt.step(
            x["q"][0],
            x["qd"][0],
            x["qdd"][0],
            x["ft"][0],
            x["positions"][0],
            **{k: v for k, v in kw.items() if k != "omega"},
        )
    with pytest.raises(InputError, match="tau_measured must have shape"):
        rt.step(
            x["q"][0],
            x["qd"][0],
            x["qdd"][0],
            x["ft"][0],
            x["positions"][0],
            **{**kw, "tau_measured": np.zeros(3)},
        )
    with pytest.raises(InputError, match="ft is missing readings"):
        rt.step(x["q"][0], x["qd"][0], x["qdd"][0], {"other": np.zeros(6)}, x["positions"][0])
    with pytest.raises(InputError, match=r"q must have shape \(1, 8\)"):
        rt.run(
            np.zeros((1, 3)), x["qd"], x["qdd"], x["ft"], x["positions"], **{k: x[k] for k in kw}
        )
    plain = exports.runtime("tcarm")
    with pytest.raises(InputError, match="no input 'omega'"):
        plain.step(*(np.zeros(7),) * 3, np.zeros((1, 6)), np.zeros((2, 3)), omega=np.zeros(3))


@pytest.fixture(scope="module")
def residuals(tmp_path_factory):
    """Correction stacks of the bundled arm (offset + MLP, offset + GRU; random weights, an extra
    column) as checkpoints and as their graphs (``export_residual_checkpoint``)."""
    from torchcontact.export import export_residual_checkpoint

    d = tmp_path_factory.mktemp("residual")
    model = robot_model("tcarm")
    out = {}
    for kind in ("mlp", "gru", "inertial"):
        ckpt = correction_checkpoint(
            d / kind, model, "base_ft", "mlp" if kind == "inertial" else kind
        )
        if kind == "inertial":  # plus an inertial layer (a parameter change of two bodies)
            from torchcontact.residual import ResidualCorrection

            c = ResidualCorrection.load(ckpt, model)
            delta = torch.randn(20, generator=torch.Generator().manual_seed(5)).double() * 0.3
            names = model.body_names
            ckpt = ResidualCorrection(
                model, "base_ft", offset=c.offset, inertial_bodies=(names[-1], names[-3]),
                delta=delta, learned=c.learned, features=c.features,
            ).save(d / "inertial-stack")  # fmt: skip
        export_residual_checkpoint(ckpt, d / f"{kind}.onnx", model)
        out[kind] = (ckpt, d / f"{kind}.onnx")
    return out


#: the learned layer runs in float32: its features are rounded to float32 (computed in float64
#: by the step graph and torch, in float32 by the stand-alone correction graph)
LEARNED_FLOAT32 = 2e-5  # N, N m: a float32 ulp of a 50 N feature, through the network


@pytest.mark.parametrize("kind", ["mlp", "gru", "inertial"])
def test_one_call_from_raw_reading_with_the_residual(exports, residuals, kind):
    """The correction inside the graph (export) or chained by the runtime: the same estimate.

    Chained by the runtime, the correction graph's own output is subtracted (reference: that
    output, then the torch estimator, 1e-9); inside the single-frame graph the stack is rebuilt
    from its layers on the graph's forward pass (reference: the torch correction stack, then the
    torch estimator, to the learned layer's float32 rounding), in a few hundred nodes.
    """
    import onnxruntime as ort

    from torchcontact.export import step_graph_path
    from torchcontact.residual import ResidualCorrection
    from torchcontact.runtime import EstimatorRuntime

    ckpt, graph = residuals[kind]
    x = scene("tcarm", 8, seed=7)
    temp = np.linspace(20.0, 40.0, 8)
    inside = EstimatorRuntime(exports.path("tcarm", residual=str(graph)), robot="tcarm")
    chained = EstimatorRuntime(exports.path("tcarm"), robot="tcarm", residual=graph)
    assert inside.extra == chained.extra == ("temperature",)
    # reference: the correction graph's own output (float32, raw joint state in), subtracted,
    # then the torch estimator in float64; a GRU keeps its state from frame to frame
    sess = ort.InferenceSession(str(graph), providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    assert names == ["q", "qd", "qdd", "extra"] + (["h_in"] if kind == "gru" else [])
    h = np.zeros((1, 1, 8), np.float32)
    fixed = dict(x)
    fixed["ft"] = x["ft"].copy()
    for i in range(8):
        feed = {k: x[k][i : i + 1].astype(np.float32) for k in ("q", "qd", "qdd")}
        feed["extra"] = np.array([[temp[i]]], np.float32)
        if kind == "gru":
            feed["h_in"] = h
        o = sess.run(None, feed)
        if kind == "gru":
            h = o[1]
        fixed["ft"][i, 0] -= o[0][0]
    # and the torch correction stack agrees with its graph (float32)
    corr = ResidualCorrection.load(ckpt, robot_model("tcarm"))
    want = corr.correction(
        *(torch.as_tensor(x[k]) for k in ("q", "qd", "qdd")), {"temperature": torch.as_tensor(temp)}
    )
    np.testing.assert_allclose(x["ft"][:, 0] - fixed["ft"][:, 0], want.numpy(), atol=1e-4)
    ref = reference("tcarm", fixed)
    native = dict(x)
    native["ft"] = x["ft"].copy()
    native["ft"][:, 0] -= want.numpy()
    ref_native = reference("tcarm", native)
    step_file = step_graph_path(exports.path("tcarm", residual=str(graph)))
    assert len(onnx.load(str(step_file)).graph.node) < 600  # the stack built natively
    for rt, rf, tol in ((inside, ref_native, LEARNED_FLOAT32), (chained, ref, 1e-9)):
        rt.reset()
        for i in range(8):
            out = rt.step(
                x["q"][i],
                x["qd"][i],
                x["qdd"][i],
                x["ft"][i],
                x["positions"][i],
                x["active"][i],
                ft_residual=x["ft_residual"][i],
                extra={"temperature": temp[i]},
            )
            np.testing.assert_allclose(out["force"], rf.force[i].numpy(), atol=tol, rtol=0)
            np.testing.assert_allclose(
                out["joint_torques"], rf.joint_torques[i].numpy(), atol=tol, rtol=0
            )
        with pytest.raises(InputError, match="temperature"):
            rt.step(x["q"][0], x["qd"][0], x["qdd"][0], x["ft"][0], x["positions"][0])
    if kind == "mlp":  # the batched graph takes the correction too
        b = inside.run(
            x["q"],
            x["qd"],
            x["qdd"],
            x["ft"],
            x["positions"],
            x["active"],
            ft_residual=x["ft_residual"],
            extra={"temperature": temp},
        )
        # the reference evaluates the correction on the same batch (float32 sums in the
        # batched MatMuls round differently from one frame at a time, ~1e-5 N)
        feed = {k: x[k].astype(np.float32) for k in ("q", "qd", "qdd")}
        (corr_b,) = sess.run(None, {**feed, "extra": temp[:, None].astype(np.float32)})
        fixed["ft"] = x["ft"].copy()
        fixed["ft"][:, 0] -= corr_b
        ref = reference("tcarm", fixed)
        np.testing.assert_allclose(b["force"], ref.force.numpy(), atol=1e-9)
        np.testing.assert_allclose(b["joint_torques"], ref.joint_torques.numpy(), atol=1e-9)


def test_residual_for_another_robot_or_sensor_is_refused(exports, residuals, tmp_path):
    from torchcontact.export import export_estimator
    from torchcontact.runtime import EstimatorRuntime

    _, graph = residuals["mlp"]
    m = onnx.load(str(graph))
    for p in m.metadata_props:
        if p.key == "sensor":
            p.value = "wrist_ft"
    onnx.save(m, str(tmp_path / "wrist.onnx"))
    with pytest.raises(ModelMismatchError, match="corrects sensor 'wrist_ft'"):
        EstimatorRuntime(exports.path("tcarm"), residual=tmp_path / "wrist.onnx")
    lay = LAYOUTS["panda"]
    with pytest.raises(ModelMismatchError, match="trained on a robot"):
        export_estimator(
            robot_model("panda"),
            None,
            lay["links"],
            lay["kinds"],
            tmp_path / "p.onnx",
            residual=graph,
        )
    with pytest.raises(ModelMismatchError, match="already holds"):
        EstimatorRuntime(exports.path("tcarm", residual=str(graph)), residual=graph)


def test_two_sensors_stacks_built_natively_equal_the_chained_graphs(tmp_path):
    """Two sensors, each with a stack (offset, inertial layer, MLP), built natively in the step
    graph (one Newton-Euler stage for the nominal and both changed inertias, each correction
    taken off its reading before the move to the root frame) against the same stacks' graphs
    chained by the runtime; float64, covariance, every slot kind (``tcarm2``), to the stack
    graphs' float32 rounding. Fixed base: a stack's own graph models a fixed base (it has no
    base-motion inputs), the native build uses the graph's base motion."""
    from torchcontact.export import export_estimator, export_residual_checkpoint, step_graph_path
    from torchcontact.residual import ResidualCorrection
    from torchcontact.runtime import EstimatorRuntime

    model = robot_model("tcarm2")
    lay = LAYOUTS["tcarm2"]
    names = model.body_names
    graphs = []
    for s, (sensor, bodies) in enumerate(
        (("base_ft", (names[-1], names[-3])), ("tool_ft", (names[-1],)))
    ):
        c = ResidualCorrection.load(
            correction_checkpoint(tmp_path / f"c{s}", model, sensor, "mlp", seed=4 + s), model
        )
        g = torch.Generator().manual_seed(9 + s)
        ckpt = ResidualCorrection(
            model, sensor, offset=c.offset, inertial_bodies=bodies, learned=c.learned,
            delta=torch.randn(10 * len(bodies), generator=g).double() * 0.3, features=c.features,
        ).save(tmp_path / f"stack{s}")  # fmt: skip
        export_residual_checkpoint(ckpt, tmp_path / f"stack{s}.onnx", model)
        graphs.append(str(tmp_path / f"stack{s}.onnx"))
    paths = []
    for name, res in (("inside", graphs), ("plain", None)):
        paths.append(tmp_path / f"{name}.onnx")
        export_estimator(model, None, lay["links"], lay["kinds"], paths[-1], covariance=True,
                         residual=res)  # fmt: skip
    ops = [n.op_type for n in onnx.load(str(step_graph_path(paths[0]))).graph.node]
    assert len(ops) < 600  # built natively
    inside = EstimatorRuntime(paths[0], robot=model)
    chained = EstimatorRuntime(paths[1], robot=model, residual=graphs)
    x = scene("tcarm2", 6, seed=11)
    keys = ("positions", "active", "directions", "wrenches", "ft_cov", "ft_residual")
    for i in range(6):
        kw = {k: x[k][i] for k in keys}
        extra = {"temperature": 25.0 + i}
        a, b = (
            rt.step(x["q"][i], x["qd"][i], x["qdd"][i], x["ft"][i], **kw, extra=extra)
            for rt in (inside, chained)
        )
        assert not np.allclose(a["force"], 0.0)
        for k in ("force", "joint_torques", "covariance"):
            np.testing.assert_allclose(a[k], b[k], atol=LEARNED_FLOAT32 * 10, rtol=0, err_msg=k)
