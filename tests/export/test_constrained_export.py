"""The friction-cone constrained estimator as an ONNX graph (``export_estimator(...,
constraints=...)``), run by the runtime: parity with the eager torch estimator."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchcontact as tc

pytest.importorskip("onnxruntime")

#: a small budget keeps the unrolled graph quick to trace (25 iterations: ~2 min); with 3
#: iterations no frame stops early in torch either, so both run the same arithmetic
ITERATIONS = 3


def test_constrained_graph_matches_the_torch_estimator(tmp_path):
    from torchcontact.export import CONE_INPUTS, CONE_OUTPUTS, export_estimator
    from torchcontact.runtime import EstimatorRuntime

    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    links, kinds = ("forearm_skin", "hand_skin"), ("force", "force")
    cones = tc.FrictionCones(ITERATIONS)
    path = tmp_path / "cones.onnx"
    export_estimator(model, ["base_ft"], links, kinds, path, dtype=torch.float64,
                     constraints=cones)  # fmt: skip
    rt = EstimatorRuntime(path, expect_joint_names=model.joint_names)
    assert rt.metadata["constraints"]["iterations"] == ITERATIONS
    assert {*CONE_INPUTS} <= set(rt.metadata["inputs"])
    assert {*CONE_OUTPUTS} <= set(rt.metadata["outputs"])

    g = torch.Generator().manual_seed(0)
    n, f64 = 64, torch.float64
    q, qd, qdd = (torch.rand(n, model.nv, generator=g, dtype=f64) - 0.5 for _ in range(3))
    pos = (torch.rand(n, 2, 3, generator=g, dtype=f64) - 0.5) * 0.05
    normals = torch.randn(n, 2, 3, generator=g, dtype=f64)
    ft = torch.randn(n, 6, generator=g, dtype=f64) * 5
    friction = torch.full((n, 2), 0.5, dtype=f64)
    pushing = torch.ones(n, 2, dtype=torch.bool)
    est = tc.ContactEstimator(model, ["base_ft"])
    c = tc.Contacts(links, kinds, pos, normals=normals, friction=friction, pushing=pushing)
    ref = est.estimate(q, qd, qdd, {"base_ft": ft}, c, constraints=cones, backend="eager")
    out = rt.run(q.numpy(), qd.numpy(), qdd.numpy(), ft[:, None].numpy(), pos.numpy(),
                 normals=normals.numpy(), friction=friction.numpy(),
                 pushing=pushing.numpy().astype(np.float64))  # fmt: skip
    free = est.estimate(q, qd, qdd, {"base_ft": ft}, c, backend="eager")
    moved = (ref.force - free.force).norm(dim=-1).amax(-1) > 1e-3
    assert moved.sum() > n // 4  # the cones changed the pseudo-inverse's answer on these frames
    np.testing.assert_allclose(out["force"], ref.force.numpy(), atol=1e-9)
    np.testing.assert_array_equal(out["cone_active"], ref.cones.active.numpy())
    np.testing.assert_array_equal(out["iterations"][:, 0], ref.cones.iterations["base_ft"].numpy())
    np.testing.assert_array_equal(out["converged"][:, 0], ref.cones.converged["base_ft"].numpy())
    # 3 iterations: no frame converges, status 256 (a warning, outputs kept) in both
    np.testing.assert_array_equal(out["status"], ref.status.numpy())
    np.testing.assert_array_equal(out["status"] == 256, ~ref.cones.converged["base_ft"].numpy())
