"""``export estimator --localize LINK``: contact localization inside the single-frame graph.

Reference: :class:`torchcontact.localize.Localizer` (ray casting in torch, its own line
program) frame by frame, then :meth:`ContactEstimator.estimate` with the localized contact on
LINK's ``force`` slot; the graph runs in float32 through onnxruntime (tolerances: 2e-5 m on
points of a 6 cm box, 2e-3 N / N m on forces and torques of 5-20 N contacts).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import torchcontact as tc
from torchcontact.errors import InputError
from torchcontact.export import export_estimator
from torchcontact.localize import Localizer
from torchcontact.meshes import LinkMesh

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("onnxruntime")

LINK = "hand"
LINKS, KINDS = ["forearm", LINK], ["force", "force"]
THRESHOLD = 2.0
#: per graph dtype: points (m), forces and torques (N, N m)
TOL = {torch.float32: {"point": 2e-5, "force": 2e-3}, torch.float64: {"point": 1e-9, "force": 1e-8}}


@pytest.fixture(scope="module")
def arm():
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path())


def _box_mesh(model, size=0.06, center=(0.0, 0.0, 0.03)):
    b = trimesh.creation.box(extents=(size,) * 3)
    fr = model.frame(LINK)
    return LinkMesh(LINK, fr.body, np.asarray(b.vertices) + center, np.asarray(b.faces, np.int64),
                    fr.R_body_frame, fr.p_body_frame, None, ("test box",))  # fmt: skip


def _frames(model, mesh, n, seed=0):
    """Random joint states; pushes at points of the box (some below the threshold, some lines
    that miss it, some frames with skin contact on LINK or on the other slot)."""
    rng = np.random.default_rng(seed)
    q = torch.as_tensor(rng.uniform(-1, 1, (n, model.nv)))
    qd = torch.as_tensor(rng.uniform(-1, 1, (n, model.nv)))
    qdd = torch.as_tensor(rng.uniform(-2, 2, (n, model.nv)))
    tri = mesh.vertices[mesh.faces]
    k = rng.integers(len(tri), size=n)
    pts = np.einsum("nk,nki->ni", rng.dirichlet([1, 1, 1], size=n), tri[k])
    nrm = mesh.face_normals()[k]
    f = -(nrm + 0.3 * rng.normal(size=(n, 3))) * rng.uniform(5, 20, (n, 1))
    f[1] *= 0.01  # below the threshold
    f[2] = rng.normal(size=3) * 10  # a random line, pushing or missing
    est = tc.ContactEstimator(model)
    w = torch.as_tensor(np.c_[f, np.zeros((n, 3))])[:, None]
    c = tc.Contacts([LINK], ["known"], torch.as_tensor(pts)[:, None], wrenches=w)
    ft = est.predict_ft(q, qd, qdd, c)
    positions = np.zeros((n, 2, 3))
    positions[:, 1] = pts
    positions[:, 0] = [0.02, 0.0, 0.1]
    active = np.zeros((n, 2), bool)
    active[3, 1] = True  # skin reports the contact on LINK: the skin wins
    active[4, 0] = True  # skin contact elsewhere in the region: no localization
    return q, qd, qdd, ft, positions, active


@pytest.mark.parametrize(
    "options", [{}, {"dtype": torch.float64, "joints": "sensed"}], ids=["float32", "float64-sensed"]
)
def test_step_graph_localizes_like_the_localizer_and_the_estimator(arm, tmp_path, options):
    from torchcontact.runtime import EstimatorRuntime

    mesh = _box_mesh(arm)
    out = tmp_path / "est.onnx"
    meta = export_estimator(arm, None, LINKS, KINDS, out, localize=LINK, meshes={LINK: mesh},
                            localize_threshold=THRESHOLD, **options)  # fmt: skip
    tol = TOL[options.get("dtype", torch.float32)]
    loc_meta = json.loads(meta["localize"])
    assert loc_meta["link"] == LINK and loc_meta["mesh"] == "collision mesh (12 faces)"
    n = 24
    q, qd, qdd, ft, positions, active = _frames(arm, mesh, n)
    # the reference: the localizer, then the estimator with the localized contact on LINK
    ref = Localizer(arm, {LINK: mesh}, links=[LINK], ray="torch", friction=None,
                    snap_distance=0.0, force_threshold=THRESHOLD).localize(q, qd, qdd, ft)  # fmt: skip
    ref = ref["base_ft"]
    skin = active.any(1)
    used = (ref.link.numpy() >= 0) & ~skin
    pos = positions.copy()
    pos[used, 1] = ref.position.numpy()[used]
    act = active.copy()
    act[used, 1] = True
    want = tc.ContactEstimator(arm).estimate(
        q, qd, qdd, ft, tc.Contacts(LINKS, KINDS, torch.as_tensor(pos), active=torch.as_tensor(act))
    )
    rt = EstimatorRuntime(out.with_name("est.step.onnx"), robot=arm)
    statuses = []
    for i in range(n):
        got = rt.step({"q": q[i].numpy(), "qd": qd[i].numpy(), "qdd": qdd[i].numpy(),
                       "ft": ft["base_ft"][i].numpy()[None], "positions": positions[i],
                       "active": active[i].astype(float)})  # fmt: skip
        assert got["status"] == int(want.status[i])
        status = got["localize_status"]
        statuses.append(status)
        assert status == (int(ref.status[i]) & ~16) | (32 if skin[i] else 0)
        if used[i]:
            np.testing.assert_allclose(got["localize_position"], ref.position[i], atol=tol["point"])
        else:
            assert np.isnan(got["localize_position"]).all()
        np.testing.assert_allclose(got["force"], want.force[i], atol=tol["force"])
        np.testing.assert_allclose(got["moment"], want.moment[i], atol=tol["force"])
        np.testing.assert_allclose(got["joint_torques"], want.joint_torques[i], atol=tol["force"])
        assert got["rank"][0] == want.rank["base_ft"][i]
        assert got["unknowns"][0] == want.unknowns["base_ft"][i]
        np.testing.assert_allclose(got["residual"][0], want.residual["base_ft"][i], atol=1e-3)
    # every case happened: localized, below the threshold, skin on LINK, skin elsewhere
    assert statuses[1] == 2 and statuses[3] & 32 and statuses[4] & 32
    assert used.sum() >= n // 2
    # the localized contact carries the force (the skin-free estimate would be zero there)
    assert np.abs(want.force.numpy()[used][:, 1]).max() > 5.0


def test_a_large_mesh_is_replaced_by_its_convex_hull(arm, tmp_path):
    from torchcontact.onnx.step.localize import localize_link

    est = tc.ContactEstimator(arm)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.03)  # 1280 faces
    fr = arm.frame(LINK)
    v = np.asarray(sphere.vertices).copy()
    v[1::2] *= 0.8  # dents: half the vertices inside the hull
    mesh = LinkMesh(LINK, fr.body, v, np.asarray(sphere.faces),
                    fr.R_body_frame, fr.p_body_frame, None, ())  # fmt: skip
    spec = localize_link(arm, est.layout((), ()), LINKS, KINDS, LINK, {LINK: mesh}, 1.0, 2000)
    assert spec.mesh is mesh and spec.mesh_choice == "collision mesh (1280 faces)"
    spec = localize_link(arm, est.layout((), ()), LINKS, KINDS, LINK, {LINK: mesh}, 1.0, 1000)
    assert spec.mesh_choice.startswith("convex hull (") and len(spec.mesh.faces) <= 1000
    with pytest.raises(InputError, match="raise it"):
        localize_link(arm, est.layout((), ()), LINKS, KINDS, LINK, {LINK: mesh}, 1.0, 100)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--slot", "hand:force", "--localize", "base_link"], "outside the subtree"),
        (["--slot", "hand:force", "--localize", "hand"], "no collision geometry"),
        (["--slot", "hand:wrench", "--localize", "hand"], "no force slot on hand"),
        (["--slot", "hand:force", "--localize", "nope"], "not a link of tcarm"),
    ],
)
def test_cli_refuses_bad_localize_links(tmp_path, capsys, argv, message):
    from export.__main__ import main

    code = main(["estimator", "--robot", "tcarm", *argv, "--out", str(tmp_path / "e.onnx")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert err[-1].startswith("error:") and message in err[-1]
    assert not (tmp_path / "e.onnx").exists()


def test_a_localized_contact_is_not_contact_free_for_the_bias_tracker(arm, tmp_path):
    from torchcontact.runtime import EstimatorRuntime

    mesh = _box_mesh(arm)
    q, qd, qdd, ft, positions, _ = _frames(arm, mesh, 6)
    rts = {}
    for name, kw in (("plain", {}), ("loc", dict(localize=LINK, meshes={LINK: mesh}))):
        export_estimator(arm, None, LINKS, KINDS, tmp_path / f"{name}.onnx", online=True, **kw)
        rts[name] = EstimatorRuntime(tmp_path / f"{name}.step.onnx", robot=arm, track_bias=True)
    for i in (0, 1):  # a push on LINK's mesh (localized), then a force below the threshold
        x = {"q": q[i].numpy(), "qd": qd[i].numpy(), "qdd": qdd[i].numpy(),
             "ft": ft["base_ft"][i].numpy()[None], "positions": positions[i],
             "active": np.zeros(2)}  # fmt: skip
        plain, loc = rts["plain"].step(x, t=0.01 * i), rts["loc"].step(x, t=0.01 * i)
        assert plain["bias"].updated[0]  # no slot active: the plain step takes it as free
        assert loc["localize_status"] == (0 if i == 0 else 2)
        assert loc["bias"].updated[0] == (i == 1)  # the localized contact is a contact
