"""The noise-weighted export (``export estimator --ft-noise``): graphs and C step, weighted.

An estimator exported with ``ft_noise`` whitens each sensor's rows by its noise, constants of the
graph, before the pivoted solve (:mod:`torchcontact.onnx.step.solve`,
:func:`torchcontact.estimation.programs.estimate_program`). It must compute
``ContactEstimator.estimate(ft_covariance=diag(std^2), weighted=True)`` (float64, ``PARITY``:
1e-9) in the single-frame graph, the batched graph and the C step's program, agree with a numpy
weighted least squares of minimum norm on rank-deficient frames, and leave an unweighted export
as it was.
"""

from __future__ import annotations

import hashlib

import numpy as np
import onnx
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

#: Per layout the ``--ft-noise`` values: unequal axes, so the weighting changes the answer.
NOISE = {
    "tcarm": ("base_ft=0.1,0.2,0.15,0.005,0.004,0.006",),
    "icub": ("l_arm_ft=0.1,0.005",),
}
STD = {
    "tcarm": {"base_ft": (0.1, 0.2, 0.15, 0.005, 0.004, 0.006)},
    "icub": {"l_arm_ft": (0.1,) * 3 + (0.005,) * 3},
}
SLOT_INPUTS = ("positions", "active", "directions", "wrenches", "ft_residual")


def _weighted_reference(
    name: str, x: dict, rt=None, covariance: bool = False, dtype=np.float64
) -> tc.ContactEstimate:
    """The torch estimator's weighted estimate, ``ft_covariance = diag(std^2)`` (float64).

    ``dtype``: the graph dtype whose rank rule applies.
    """
    lay = LAYOUTS[name]
    est = reference_estimator(name, dtype)
    t = {k: torch.as_tensor(v) for k, v in x.items() if k != "truth"}
    ft = {s: t["ft"][:, i] - t["ft_residual"][:, i] for i, s in enumerate(est.sensor_names)}
    c = tc.Contacts(lay["links"], lay["kinds"], t["positions"], t["directions"], t["wrenches"],
                    t["active"] > 0.5)  # fmt: skip
    cov = {s: torch.diag(torch.tensor(sd, dtype=torch.float64) ** 2) for s, sd in STD[name].items()}
    ref = est.estimate(t["q"], t["qd"], t["qdd"], ft, c, backend="eager", ft_covariance=cov,
                       weighted=True, covariance=covariance)  # fmt: skip
    if rt is not None:  # NaN for the joints whose torques the graph does not output
        keep = {rt.joint_names.index(j) for j in rt.metadata["torque_joints"]}
        tau = ref.joint_torques.clone()
        tau[:, [c for c in range(rt.nv) if c not in keep]] = float("nan")
        ref = ref._replace(joint_torques=tau)
    return ref


@pytest.mark.parametrize("name", ["tcarm", "icub"])
def test_weighted_graphs_equal_the_weighted_estimate(exports, name):
    """Single-frame graph on both layouts, the batched graph on tcarm (its session is slow)."""
    x = scene(name, 12, seed=5)
    rt = exports.runtime(name, np.float64, ft_noise=NOISE[name])
    assert rt.ft_noise == STD[name] and "weighted by ft_noise" in repr(rt)
    ref = _weighted_reference(name, x, rt)
    sensors = list(STD[name])
    # the weighting matters on these frames (else the test could not fail)
    plain = reference(name, x)
    assert np.nanmax(np.abs(plain.force.numpy() - ref.force.numpy())) > 1e-3
    kw = {k: x[k] for k in SLOT_INPUTS}
    steps = [rt.step(x["q"][i], x["qd"][i], x["qdd"][i], x["ft"][i],
                     **{k: v[i] for k, v in kw.items()}) for i in range(len(x["q"]))]  # fmt: skip
    stacked = {k: np.stack([np.asarray(o[k]) for o in steps]) for k in steps[0]}
    assert_parity(stacked, ref, sensors, np.float64)
    if name == "tcarm":
        out = rt.run(x["q"], x["qd"], x["qdd"], x["ft"], **kw)
        assert_parity(out, ref, sensors, np.float64)


def test_float32_step_graph_eliminates_the_weighted_system_in_float64(exports):
    """The whitened system's spread of scales: a float32 elimination lost up to 2.5e-2."""
    name = "tcarm"
    x = scene(name, 24, seed=11)
    rt = exports.runtime(name, np.float32, ft_noise=NOISE[name])
    ref = _weighted_reference(name, x, rt, dtype=np.float32)
    kw = {k: x[k] for k in SLOT_INPUTS}
    steps = [rt.step(x["q"][i], x["qd"][i], x["qdd"][i], x["ft"][i],
                     **{k: v[i] for k, v in kw.items()}) for i in range(len(x["q"]))]  # fmt: skip
    stacked = {k: np.stack([np.asarray(o[k]) for o in steps]) for k in steps[0]}
    assert_parity(stacked, ref, list(STD[name]), np.float32)


def test_covariance_of_the_weighted_step_graph(tmp_path):
    """``--covariance --ft-noise``: ``ft_cov`` propagated through the weighted solve."""
    from torchcontact.export import export_estimator
    from torchcontact.runtime import EstimatorRuntime

    name = "tcarm"
    lay, std = LAYOUTS[name], STD[name]["base_ft"]
    path = tmp_path / "cov.onnx"
    export_estimator(robot_model(name), None, lay["links"], lay["kinds"], path,
                     dtype=torch.float64, covariance=True, ft_noise=NOISE[name])  # fmt: skip
    rt = EstimatorRuntime(path)
    x = scene(name, 8, seed=5)
    cov = np.diag(np.square(std))  # the noise the graph is weighted by: the library's case
    ref = _weighted_reference(name, x, covariance=True)
    for i in range(len(x["q"])):
        got = rt.step(x["q"][i], x["qd"][i], x["qdd"][i], x["ft"][i], ft_cov=cov[None],
                      **{k: x[k][i] for k in SLOT_INPUTS})  # fmt: skip
        np.testing.assert_allclose(got["covariance"], ref.covariance[i], rtol=0, atol=1e-10)
        np.testing.assert_allclose(got["force"], ref.force[i], rtol=0, atol=1e-8)


def test_rank_deficient_frames_equal_numpy_weighted_least_squares(exports):
    """Two pure forces on one region (rank 5 of 6): ``pinv(W A) W b``, W = diag(1 / std)."""
    name = "tcarm"
    x = scene(name, 6, seed=7, patterns=((1, 1),))
    rt = exports.runtime(name, np.float64, ft_noise=NOISE[name])
    lay, est = LAYOUTS[name], reference_estimator(name)
    t = {k: torch.as_tensor(v) for k, v in x.items() if k != "truth"}
    K = len(lay["links"])
    W = np.diag(1.0 / np.array(STD[name]["base_ft"]))
    for i in range(len(x["q"])):
        q, qd, qdd = (t[k][i : i + 1] for k in ("q", "qd", "qdd"))

        def reading(wr: torch.Tensor, q=q, qd=qd, qdd=qdd, i=i) -> np.ndarray:
            c = tc.Contacts(lay["links"], ("known",) * K, t["positions"][i : i + 1], wrenches=wr)
            return est.predict_ft(q, qd, qdd, c)["base_ft"][0].numpy()

        # A by linearity of the model's reading in the contact forces, b = ft - contact-free
        zero = torch.zeros(1, K, 6, dtype=torch.float64)
        r0 = reading(zero)
        A = np.zeros((6, 3 * K))
        for j in range(3 * K):
            unit = zero.clone()
            unit[0, j // 3, j % 3] = 1.0
            A[:, j] = reading(unit) - r0
        b = x["ft"][i, 0] - x["ft_residual"][i, 0] - r0
        sv = np.linalg.svd(A, compute_uv=False)
        assert sv[4] > 1e-3 * sv[0] and sv[5] < 1e-12 * sv[0]  # rank 5: one direction unseen
        want = np.linalg.pinv(W @ A, rcond=1e-8) @ (W @ b)
        got = rt.step(x["q"][i], x["qd"][i], x["qdd"][i], x["ft"][i],
                      **{k: x[k][i] for k in SLOT_INPUTS})  # fmt: skip
        assert int(np.asarray(got["rank"]).reshape(-1)[0]) == 5
        np.testing.assert_allclose(got["force"].reshape(-1), want, rtol=0, atol=1e-9 * 20)
        # the unweighted minimum-norm answer differs: the weighting is what is tested
        assert np.abs(np.linalg.pinv(A) @ b - want).max() > 1e-3


def test_c_step_is_weighted_alike(tmp_path):
    """``export estimator --format c --ft-noise``: the program the library compiles, evaluated.

    The C source is this program emitted by :mod:`torchcontact.kernels._cabi`, whose kernels are
    compared with eager torch elsewhere; building a weighted library here would cost seconds of
    compilation (it was checked once: 7.6e-14 N from the weighted estimate, docs/deployment.md).
    """
    import json

    from torchcontact.kernels.runner import run_program
    from torchcontact.online.cstep import InertialCorrection, export_c_step, step_program

    name = "tcarm"
    x = scene(name, 8, seed=5)
    lay, est = LAYOUTS[name], reference_estimator(name)
    em = est.layout(lay["links"], lay["kinds"])
    corr = InertialCorrection(((),), (None,))
    prog = step_program(em, corr, range(em.tree.nv), noise=(STD[name]["base_ft"],))
    assert "ft_cov" not in prog.inputs and "noise=" in prog.key
    assert "noise" not in step_program(em, corr, range(em.tree.nv)).key
    n, K = len(x["q"]), len(lay["links"])
    ins = {"q": x["q"], "qd": x["qd"], "qdd": x["qdd"], "ft": x["ft"][:, 0] - x["ft_residual"][:, 0],
           "positions": x["positions"].reshape(n, 3 * K), "active": x["active"]}  # fmt: skip
    tensors = {k: torch.as_tensor(ins.get(k, np.zeros((n, w)))) for k, w in prog.inputs.items()}
    out = run_program(prog, tensors, backend="eager")
    ref = _weighted_reference(name, x)
    scale = float(ref.force.abs().max())
    np.testing.assert_allclose(out["force"].reshape(n, K, 3), ref.force, rtol=0, atol=1e-9 * scale)
    # the library's metadata says so (what EstimatorRuntime(backend="c").ft_noise reads)
    path = tmp_path / "w.so"
    meta = export_c_step(robot_model(name), None, lay["links"], lay["kinds"], path,
                         ft_noise=NOISE[name], build=False)  # fmt: skip
    assert meta["ft_noise"]["sensors"]["base_ft"]["std"] == list(STD[name]["base_ft"])
    assert json.loads(path.with_suffix(".json").read_text())["ft_noise"] == meta["ft_noise"]


def test_constrained_graph_is_weighted_alike(tmp_path):
    """``--constraints --ft-noise``: the cone solve on the whitened rows, as the library's."""
    from torchcontact.export import export_estimator
    from torchcontact.runtime import EstimatorRuntime

    model, f64 = robot_model("tcarm"), torch.float64
    links, kinds = ("hand_skin",), ("force",)  # one slot: the quickest graph to load
    cones = tc.FrictionCones(3)  # a small budget: quick to trace, no frame stops early
    path = tmp_path / "cones.onnx"
    export_estimator(model, None, links, kinds, path, dtype=f64, constraints=cones,
                     ft_noise=NOISE["tcarm"])  # fmt: skip
    rt = EstimatorRuntime(path)
    assert rt.ft_noise == STD["tcarm"]
    g = torch.Generator().manual_seed(0)
    n = 16
    q, qd, qdd = (torch.rand(n, model.nv, generator=g, dtype=f64) - 0.5 for _ in range(3))
    pos = (torch.rand(n, 1, 3, generator=g, dtype=f64) - 0.5) * 0.05
    normals = torch.randn(n, 1, 3, generator=g, dtype=f64)
    ft = torch.randn(n, 6, generator=g, dtype=f64) * 5
    friction = torch.full((n, 1), 0.5, dtype=f64)
    c = tc.Contacts(links, kinds, pos, normals=normals, friction=friction,
                    pushing=torch.ones(n, 1, dtype=torch.bool))  # fmt: skip
    cov = {"base_ft": torch.diag(torch.tensor(STD["tcarm"]["base_ft"], dtype=f64) ** 2)}
    est = reference_estimator("tcarm")
    ref = est.estimate(q, qd, qdd, {"base_ft": ft}, c, constraints=cones, backend="eager",
                       ft_covariance=cov)  # fmt: skip
    plain = est.estimate(q, qd, qdd, {"base_ft": ft}, c, constraints=cones, backend="eager")
    out = rt.run(q.numpy(), qd.numpy(), qdd.numpy(), ft[:, None].numpy(), pos.numpy(),
                 normals=normals.numpy(), friction=friction.numpy(),
                 pushing=np.ones((n, 1)))  # fmt: skip
    scale = float(ref.force.abs().max())
    assert float((ref.force - plain.force).abs().max()) > 1e-3 * scale  # weighting matters
    np.testing.assert_allclose(out["force"], ref.force.numpy(), rtol=0, atol=1e-9 * scale)
    np.testing.assert_array_equal(out["status"], ref.status.numpy())


def test_unweighted_export_is_unchanged(exports):
    """Without ``ft_noise`` the graphs are byte for byte the recorded ones.

    The digests are of the serialised graphs without their metadata (which holds versions), for
    the float64 ``tcarm`` layout; the batched graph's was taken from main at d499cb6, the step
    graph's after its poses became batched homogeneous products and its joint rates products with
    the motion subspaces (``onnx.step.kinematics``, issue 23: fewer nodes), then after its status
    tail and ``b`` took fewer nodes (``onnx.step.outputs``, ``onnx.step.regions``, round 6), then
    after the solve's test, residual, status tail and body wrenches did (round 8). A deliberate
    change of the graphs updates them.
    """
    want = {
        "batched": "fdc8f134055471b288ee1e2348ec0889c34ca4f395c514ddd7ebf3e7f5fb1004",
        "step": "f150369de1b1d40fac7f43684a9f2c89e6090365669fe71eb197f7f81b64635f",
    }
    path = exports.path("tcarm", np.float64)
    for kind, p in (("batched", path), ("step", path.with_name(f"{path.stem}.step.onnx"))):
        g = onnx.load(str(p))
        meta = {m.key: m.value for m in g.metadata_props}
        assert "ft_noise" not in meta and "noise-weighted" not in meta["solver"]
        del g.metadata_props[:]
        assert hashlib.sha256(g.SerializeToString(deterministic=True)).hexdigest() == want[kind]


def test_bad_noise_is_refused(tmp_path, capsys):
    from torchcontact.export import export_estimator

    m = robot_model("tcarm")
    path = tmp_path / "a.onnx"
    for noise, what in (({"base_ft": (0.1, 0.0)}, "> 0"), (("nope=0.1,0.005",), "no F/T sensor"),
                        ({}, "no noise for ['base_ft']")):  # fmt: skip
        with pytest.raises(InputError, match=what.replace("[", r"\[").replace("]", r"\]")):
            export_estimator(m, None, ["hand_skin"], ["force"], path, ft_noise=noise)
    assert not path.exists()
    # the CLI: one error line, exit 2, nothing written
    from torchcontact.cli import main

    for bad in ("base_ft=-0.1,0.005", "l_arm_ft=0.1,0.005"):
        argv = ["export", "estimator", "--robot", "tcarm", "--slot", "hand_skin:force",
                "--out", str(path), "--ft-noise", bad]  # fmt: skip
        assert main(argv) == 2
        err = capsys.readouterr().err
        errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
        assert len(errors) == 1 and "--ft-noise" in errors[0] and "Traceback" not in err, err
    assert not path.exists()
