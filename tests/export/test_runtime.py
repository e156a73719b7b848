"""torchcontact.runtime: numpy/onnxruntime only, metadata checks, step equals run."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from export_scenes import robot_model, scene


def test_runtime_does_not_import_torch():
    code = "import torchcontact.runtime, sys; assert 'torch' not in sys.modules, 'torch imported'"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def test_step_run_and_refusals(exported):
    from torchcontact.runtime import EstimatorRuntime, ModelMismatchError

    model = robot_model("tcarm")
    rt = EstimatorRuntime(exported["tcarm"], expect_robot_sha256=model.urdf_sha256,
                          expect_joint_names=model.joint_names)  # fmt: skip
    # step runs the static single-frame graph written beside the file, run the dynamic one
    assert rt.step_session is not rt.session
    assert all(d == 1 for i in rt.step_session.get_inputs() for d in i.shape[:1])
    dyn = EstimatorRuntime(exported["tcarm"], step_graph=False)
    assert dyn.step_session is dyn.session
    _, _, _, _, x, _ = scene("tcarm", 5, seed=5)
    x = {k: v.numpy() for k, v in x.items()}
    batch = rt.run(x["q"], x["qd"], x["qdd"], x["ft"], x["positions"], x["active"])
    for i in range(5):
        one = rt.step(x["q"][i], x["qd"][i], x["qdd"][i], x["ft"][i], x["positions"][i],
                      x["active"][i])  # fmt: skip
        assert one["force"].shape == (2, 3)
        # two graphs, optimised separately by onnxruntime: float32 rounding differs, most on
        # rank-deficient frames (both slots active); 1e-4 N is the float32 parity tolerance
        np.testing.assert_allclose(one["force"], batch["force"][i], atol=1e-4)
    with pytest.raises(ModelMismatchError, match="sha256"):
        EstimatorRuntime(exported["tcarm"], expect_robot_sha256="0" * 64)
    with pytest.raises(ModelMismatchError, match="joints"):
        EstimatorRuntime(exported["tcarm"], expect_joint_names=["a"] * 7)
    with pytest.raises(ModelMismatchError, match="slots"):
        EstimatorRuntime(exported["tcarm"], expect_slots=(["hand_skin"], ["force"]))
    with pytest.raises(ValueError, match="positions"):
        rt.step(x["q"][0], x["qd"][0], x["qdd"][0], x["ft"][0], np.zeros((3, 3)))
