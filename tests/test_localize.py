"""Contact localization from the F/T wrench and collision meshes (torchcontact.localize).

References: a brute-force numpy ray/triangle loop with an independent inside test (the generalised
winding number, Jacobson et al. 2013) on random star-shaped meshes; exact geometry on boxes and a
hand-made L-shaped prism (flat face, edge, vertex, concave region); finite differences for the
covariance; the readings come from the estimator's forward model (``predict_ft``), whose agreement
with iDynTree is tested in test_estimation_idyntree.py (benchmarks/localize.py validates against
iDynTree's and pinocchio's readings directly).

Tolerances: float64 1e-9 m on exact geometry; float32 1e-4 m relative to 0.1 m links.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchcontact as tc
from torchcontact.errors import InputError
from torchcontact.localize import (
    Localizer,
    TriangleSet,
    cast_brute,
    cast_bvh,
    embree_available,
    select_entries,
)
from torchcontact.meshes import LinkMesh

trimesh = pytest.importorskip("trimesh")

TOL = {torch.float64: 1e-9, torch.float32: 1e-4}


@pytest.fixture(scope="module")
def arm():
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path())


def _world_mesh(model, link, vertices_world, faces):
    """A LinkMesh of ``link`` whose vertices are given in the root frame at q = 0."""
    fp = model.forward_pass(*(torch.zeros(1, model.nv, dtype=torch.float64),) * 3)
    R, p = model.frame_pose(fp, link)
    R, p = R[0].numpy(), p[0].numpy()
    fr = model.frame(link)
    v = (np.asarray(vertices_world, float) - p) @ R  # R^T (x - p), row vectors
    return LinkMesh(link, fr.body, v, np.asarray(faces, np.int64), fr.R_body_frame,
                    fr.p_body_frame, None, ("test",))  # fmt: skip


def _box(model, link, center, size=0.1):
    b = trimesh.creation.box(extents=(size,) * 3)
    return _world_mesh(model, link, np.asarray(b.vertices) + center, b.faces)


def _l_prism(h=0.05, s=0.05):
    """An L-shaped prism (concave): the polygon (0,0) (2,0) (2,1) (1,1) (1,2) (0,2) times s."""
    poly = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], float) * s
    n = len(poly)
    v = np.r_[np.c_[poly, np.zeros(n)], np.c_[poly, np.full(n, h)]]
    faces = [[0, i + 1, i] for i in range(1, n - 1)]  # bottom (normal -z), fan from vertex 0
    faces += [[n, n + i, n + i + 1] for i in range(1, n - 1)]  # top (+z)
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i]]  # sides, outward for a CCW polygon
    return v, np.array(faces)


def _readings(model, link, point_link, force_link):
    """Readings of pure forces at points (link frame), from the estimator's forward model."""
    n = point_link.shape[0]
    q = torch.zeros(n, model.nv, dtype=model.dtype)
    est = tc.ContactEstimator(model)
    w = torch.cat([force_link, torch.zeros_like(force_link)], -1)[:, None]
    c = tc.Contacts([link], ["known"], point_link[:, None], wrenches=w)
    return q, est.predict_ft(q, q, q, c)


def _localize(loc, model, link, points, forces):
    q, ft = _readings(model, link, points, forces)
    return loc.localize(q, q, q, ft)["base_ft"]


def _hand_point(model, world):
    fp = model.forward_pass(*(torch.zeros(1, model.nv, dtype=torch.float64),) * 3)
    R, p = model.frame_pose(fp, "hand")
    return (torch.as_tensor(np.asarray(world, float)) - p[0]) @ R[0]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_flat_face_edge_and_vertex_of_a_box(arm, dtype):
    c = np.array([0.3, 0.1, 0.5])
    model = arm.to(dtype=dtype)
    mesh = _box(arm, "hand", c)
    loc = Localizer(model, {"hand": mesh}, links=["hand"])
    h = 0.05
    world = np.array([
        c + [0.01, -0.02, h],  # top face
        c + [h, 0.03, -0.01],  # +x face
        c + [h, h, 0.0],  # edge between +x and +y
        c + [h, h, h],  # vertex
        c + [-0.02, -h, 0.04],  # -y face
    ])  # fmt: skip
    dirs_world = np.array([[0.2, 0.1, -1], [-1, 0.3, 0.2], [-1, -1, 0.1], [-1, -1, -1],
                           [0.1, 1, -0.3]])  # fmt: skip
    pts = _hand_point(arm, world)
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    f_link = 7.0 * torch.as_tensor(dirs_world / np.linalg.norm(dirs_world, axis=1, keepdims=True))
    f_link = f_link @ R  # world -> link frame
    r = _localize(loc, model, "hand", pts.to(dtype), f_link.to(dtype))
    assert r.status.tolist() == [0] * 5
    assert r.candidates.tolist() == [1] * 5  # edge and vertex hits merged into one
    assert r.link.tolist() == [0] * 5
    tol = TOL[dtype]
    torch.testing.assert_close(r.position.double(), pts, atol=tol, rtol=0)
    torch.testing.assert_close(r.force.double(), f_link, atol=tol * 100, rtol=0)
    assert (r.moment_residual.double() < tol * 100).all()
    # the reported normal is the outward normal of a face the force pushes into
    assert ((r.normal.double() * f_link).sum(-1) < 0).all()
    torch.testing.assert_close(r.normal[0].double(), R.T @ torch.tensor([0, 0, 1.0],
                               dtype=torch.float64), atol=1e-6, rtol=0)  # fmt: skip


def test_pulling_force_is_refused(arm):
    c = np.array([0.3, 0.1, 0.5])
    box = _box(arm, "hand", c)
    loc = Localizer(arm, {"hand": box}, links=["hand"])
    top = _hand_point(arm, [c + [0.01, 0.02, 0.05]])
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    up = (torch.tensor([[0.0, 0.0, 6.0]], dtype=torch.float64)) @ R  # pulls the top face up
    r = _localize(loc, arm, "hand", top, up)
    # not the top face: the same line pushes up into the bottom face
    assert r.status.tolist() == [0]
    bottom = _hand_point(arm, [c + [0.01, 0.02, -0.05]])
    torch.testing.assert_close(r.position, bottom, atol=1e-9, rtol=0)
    # an open surface (a single square plate) seen from its back: no point where it pushes
    plate = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) * 0.05 + c
    mesh = _world_mesh(arm, "hand", plate, [[0, 1, 2], [0, 2, 3]])
    loc = Localizer(arm, {"hand": mesh}, links=["hand"])
    on = _hand_point(arm, [c + [0.01, 0.02, 0.0]])
    r = _localize(loc, arm, "hand", torch.cat([on, on]), torch.cat([up, -up]))
    assert r.status.tolist() == [8, 0]
    assert r.link.tolist() == [-1, 0]
    assert torch.isnan(r.position[0]).all()
    torch.testing.assert_close(r.position[1], on[0], atol=1e-9, rtol=0)


def test_concave_region_of_an_l_prism(arm):
    v, f = _l_prism()
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    c = np.array([0.3, 0.1, 0.5])
    mesh = _world_mesh(arm, "hand", v + c, f)
    loc = Localizer(arm, {"hand": mesh}, links=["hand"])
    s, h = 0.05, 0.025
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    inner = c + [1.5 * s, s, h]  # on the inner face y = s of the horizontal arm
    world_f = torch.tensor([[0.0, -5.0, 0.0], [5.0, -5.0, 0.0]], dtype=torch.float64)
    pts = _hand_point(arm, [inner, inner])
    r = _localize(loc, arm, "hand", pts, world_f @ R)
    # straight into the inner face: unique and exact
    assert r.status[0] == 0 and r.candidates[0] == 1
    torch.testing.assert_close(r.position[0], pts[0], atol=1e-9, rtol=0)
    # diagonally: the line first enters the top of the vertical arm, then the inner face
    assert r.status[1] == 16 and r.candidates[1] == 2
    first = _hand_point(arm, [c + [0.5 * s, 2 * s, h]])
    torch.testing.assert_close(r.position[1], first[0], atol=1e-9, rtol=0)


def test_two_links_on_the_line(arm):
    ca, cb = np.array([0.3, 0.1, 0.5]), np.array([0.3, 0.1, 0.8])
    meshes = {"forearm": _box(arm, "forearm", ca), "hand": _box(arm, "hand", cb)}
    loc = Localizer(arm, meshes, links=["forearm", "hand"])
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    pts = _hand_point(arm, [cb + [0.01, 0.0, -0.05], cb + [0.01, 0.0, 0.05]])
    # pushing up into the hand's bottom face: the line below first enters the forearm box
    # pushing down on the hand's top face: the hand comes first
    f = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, -4.0]], dtype=torch.float64) @ R
    r = _localize(loc, arm, "hand", pts, f)
    assert r.status.tolist() == [16, 16] and r.candidates.tolist() == [2, 2]
    assert [loc.links[i] for i in r.link.tolist()] == ["forearm", "hand"]
    torch.testing.assert_close(r.position[1], pts[1], atol=1e-9, rtol=0)
    # one link only: unambiguous
    only = Localizer(arm, meshes, links=["hand"])
    r = _localize(only, arm, "hand", pts, f)
    assert r.status.tolist() == [0, 0] and r.candidates.tolist() == [1, 1]
    torch.testing.assert_close(r.position, pts, atol=1e-9, rtol=0)


def test_nan_frame_weak_force_miss_and_batch_shapes(arm):
    c = np.array([0.3, 0.1, 0.5])
    loc = Localizer(arm, {"hand": _box(arm, "hand", c)}, links=["hand"], force_threshold=0.5)
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    pts = _hand_point(arm, [c + [0.01 * i, -0.02, 0.05] for i in range(6)])
    f = torch.tensor([[0.1 * i, 0.2, -3.0 - i] for i in range(6)], dtype=torch.float64) @ R
    f[4] = f[4] / 100  # below the threshold
    q, ft = _readings(arm, "hand", pts, f)
    far = _hand_point(arm, [c + [1.0, 0.0, 0.0]])  # a force far from the box: misses it
    ft5 = _readings(arm, "hand", far, f[5:])[1]["base_ft"]
    ft["base_ft"][5] = ft5[0]
    q = q.clone()
    q[2, 3] = float("nan")
    r = loc.localize(q, q, q, ft)["base_ft"]
    assert r.status.tolist() == [0, 0, 1, 0, 2, 4]
    assert r.link.tolist() == [0, 0, -1, 0, -1, -1]
    assert torch.isnan(r.position[[2, 4, 5]]).all() and torch.isnan(r.wrench[2]).all()
    assert torch.isfinite(r.position[[0, 1, 3]]).all()
    torch.testing.assert_close(r.position[[0, 1, 3]], pts[[0, 1, 3]], atol=1e-9, rtol=0)
    assert not torch.allclose(r.position[0], r.position[1])  # batch elements differ
    # batch shapes (), (1,), (7,), (2, 3): batched equals frame by frame
    q0 = torch.zeros(arm.nv, dtype=torch.float64)
    ft0 = {"base_ft": ft["base_ft"][0]}
    r0 = loc.localize(q0, q0, q0, ft0)["base_ft"]
    assert r0.status.shape == () and r0.position.shape == (3,)
    torch.testing.assert_close(r0.position, pts[0], atol=1e-9, rtol=0)
    pts7 = _hand_point(arm, [c + [0.04 - 0.01 * i, 0.01 * i - 0.03, 0.05] for i in range(7)])
    f7 = torch.tensor([[0.05 * i, -0.1, -2.0 - i] for i in range(7)], dtype=torch.float64) @ R
    q7, ft7 = _readings(arm, "hand", pts7, f7)
    r7 = loc.localize(q7, q7, q7, ft7)["base_ft"]
    for shape in [(1,), (7,)]:
        n = shape[0]
        rb = loc.localize(q7[:n], q7[:n], q7[:n], {"base_ft": ft7["base_ft"][:n]})["base_ft"]
        assert rb.position.shape == (n, 3)
        torch.testing.assert_close(rb.position, r7.position[:n], atol=1e-12, rtol=0)
    q23 = q7[:6].reshape(2, 3, -1)
    r23 = loc.localize(q23, q23, q23, {"base_ft": ft7["base_ft"][:6].reshape(2, 3, 6)})
    r23 = r23["base_ft"]
    assert r23.position.shape == (2, 3, 3) and r23.status.shape == (2, 3)
    assert r23.covariance is None and r23.position_std is None
    torch.testing.assert_close(r23.position.reshape(6, 3), r7.position[:6], atol=1e-12, rtol=0)
    for i in range(6):
        one = loc.localize(q7[i], q7[i], q7[i], {"base_ft": ft7["base_ft"][i]})["base_ft"]
        torch.testing.assert_close(one.position, r7.position[i], atol=1e-12, rtol=0)


# ------------------------------------------------------------------ random meshes vs numpy
def _star_mesh(rng, scale=0.05):
    """A closed star-shaped mesh: an icosphere with random radii (concave in places)."""
    s = trimesh.creation.icosphere(subdivisions=2)
    v = np.asarray(s.vertices) * (scale * rng.uniform(0.6, 1.4, (len(s.vertices), 1)))
    return v, np.asarray(s.faces)


def _winding(points, v, f):
    """Generalised winding number of a closed triangle mesh at points (Van Oosterom-Strackee)."""
    a = v[f[:, 0]][None] - points[:, None]
    b = v[f[:, 1]][None] - points[:, None]
    c = v[f[:, 2]][None] - points[:, None]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc
           + np.einsum("pfi,pfi->pf", b, c) * la + np.einsum("pfi,pfi->pf", c, a) * lb)  # fmt: skip
    return (2 * np.arctan2(det, den)).sum(-1) / (4 * np.pi)


def _numpy_reference(o, d, meshes):
    """First entry of the line o + t d into the union of closed meshes, one line at a time.

    Plane intersection, then the point is inside a triangle when it lies on the inner side of
    its three edges (a different test from Moller-Trumbore's); inside the union by the winding
    number of a point just before the entry.
    """
    hits = []
    for li, (v, f) in enumerate(meshes):
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        n = np.cross(b - a, c - a)
        den = n @ d
        ok = np.abs(den) > 1e-15
        t = np.where(ok, ((a - o) * n).sum(1) / np.where(ok, den, 1.0), np.nan)
        p = o + t[:, None] * d
        inside = ok.copy()
        for x, y in ((a, b), (b, c), (c, a)):
            inside &= (np.cross(y - x, p - x) * n).sum(1) >= -1e-12 * (n * n).sum(1)
        hits += [(t[k], li, den[k] < 0) for k in np.flatnonzero(inside)]
    entries = sorted((t, li) for t, li, ent in hits if ent)
    out = []
    for t, li in entries:
        before = (o + (t - 1e-6) * d)[None]
        if all(_winding(before, v, f)[0] < 0.5 for v, f in meshes):
            if not out or t - out[-1][0] > 1e-3:
                out.append((t, li))
    return out


def test_against_brute_force_numpy_on_random_meshes():
    rng = np.random.default_rng(3)
    meshes = [_star_mesh(rng), _star_mesh(rng)]
    meshes[1] = (meshes[1][0] + [0.06, 0.0, 0.0], meshes[1][1])  # overlaps the first
    lm = [LinkMesh(f"l{i}", 1, v, f, np.eye(3), np.zeros(3), None, ()) for i, (v, f) in
          enumerate(meshes)]  # fmt: skip
    ts = TriangleSet.build(lm)
    n = 120
    o = rng.uniform(-0.08, 0.12, (n, 3)) * [1, 0.4, 0.4]
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # both links see every line: rays (frame, link)
    orig = torch.as_tensor(np.repeat(o, 2, 0))
    dirs = torch.as_tensor(np.repeat(d, 2, 0))
    ray_link = torch.arange(2).repeat(n)
    group = torch.arange(n).repeat_interleave(2)
    hb, hv = cast_brute(ts, orig, dirs, ray_link), cast_bvh(ts, orig, dirs, ray_link)
    key = lambda h: sorted(zip(h.ray.tolist(), h.tri.tolist(), strict=False))  # noqa: E731
    assert key(hb) == key(hv) and len(hb.ray) > n  # the tree finds exactly the brute-force hits
    sel = select_entries(hv, group, n, 1e-3, 1e-9)  # every entry (no friction cone)
    found = 0
    for i in range(n):
        ref = _numpy_reference(o[i], d[i], meshes)
        assert sel.candidates[i].item() == len(ref), i
        assert bool(sel.found[i]) == bool(ref)
        if ref:
            found += 1
            assert abs(sel.t[i].item() - ref[0][0]) < 1e-9
            assert ray_link[sel.ray[i]].item() == ref[0][1]
    assert found > n // 3


@pytest.mark.parametrize("ray", ["brute", "embree"])
def test_ray_backends_agree(arm, ray):
    if ray == "embree" and not embree_available():
        pytest.skip("embreex is not installed")  # the optional Embree backend only
    rng = np.random.default_rng(5)
    v, f = _star_mesh(rng)
    c = np.array([0.3, 0.1, 0.5])
    mesh = _world_mesh(arm, "hand", v + c, f)
    tri = v[f] + c
    k = rng.integers(len(f), size=50)
    w = rng.dirichlet([1, 1, 1], size=50)
    world = np.einsum("nk,nki->ni", w, tri[k])
    nrm = np.cross(tri[k, 1] - tri[k, 0], tri[k, 2] - tri[k, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    fw = -(nrm + 0.3 * rng.normal(size=(50, 3))) * 5
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    pts, fl = _hand_point(arm, world), torch.as_tensor(fw) @ R
    q, ft = _readings(arm, "hand", pts, fl)
    ref = Localizer(arm, {"hand": mesh}, links=["hand"], ray="torch").localize(q, q, q, ft)
    ref = ref["base_ft"]
    other = Localizer(arm, {"hand": mesh}, links=["hand"], ray=ray).localize(q, q, q, ft)
    other = other["base_ft"]
    assert torch.equal(ref.status, other.status) and torch.equal(ref.link, other.link)
    tol = 1e-9 if ray == "brute" else 1e-5  # Embree finds the triangle, the point is exact
    torch.testing.assert_close(ref.position, other.position, atol=tol, rtol=0, equal_nan=True)
    ok = ref.status == 0
    assert ok.sum() > 25
    # where unambiguous the true point is found
    torch.testing.assert_close(ref.position[ok & (ref.candidates == 1)],
                               pts[ok & (ref.candidates == 1)], atol=1e-9, rtol=0)  # fmt: skip


def test_covariance_matches_finite_differences(arm):
    c = np.array([0.3, 0.1, 0.5])
    loc = Localizer(arm, {"hand": _box(arm, "hand", c)}, links=["hand"])
    pts = _hand_point(arm, [c + [0.01, -0.02, 0.05]])
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    f = torch.tensor([[0.5, 0.3, -4.0]], dtype=torch.float64) @ R
    q, ft = _readings(arm, "hand", pts, f)
    sigma = torch.diag(torch.tensor([0.1, 0.2, 0.1, 0.005, 0.004, 0.006]) ** 2).double()
    r = loc.localize(q, q, q, ft, ft_covariance={"base_ft": sigma})["base_ft"]
    # J by central differences of the whole localization in the reading
    J = torch.zeros(3, 6, dtype=torch.float64)
    h = 1e-6
    for j in range(6):
        e = torch.zeros(6, dtype=torch.float64)
        e[j] = h
        rp = loc.localize(q, q, q, {"base_ft": ft["base_ft"] + e})["base_ft"].position[0]
        rm = loc.localize(q, q, q, {"base_ft": ft["base_ft"] - e})["base_ft"].position[0]
        J[:, j] = (rp - rm) / (2 * h)
    ref = J @ sigma @ J.T
    torch.testing.assert_close(r.covariance[0], ref, atol=1e-12, rtol=1e-5)
    assert r.position_std[0] == pytest.approx(float(torch.trace(ref).sqrt()), rel=1e-5)
    # the point moves in the face's plane only
    nrm = r.normal[0]
    assert abs(float(nrm @ r.covariance[0] @ nrm)) < 1e-15


def test_bad_input_is_named(arm, tmp_path):
    box = _box(arm, "hand", np.zeros(3))
    with pytest.raises(InputError, match="not links of"):
        Localizer(arm, {"hand": box}, links=["hand", "nope"])
    with pytest.raises(InputError, match="outside the subtree"):
        Localizer(arm, {"hand": box}, links=["base_link"])
    with pytest.raises(InputError, match=r"\['forearm'\] have no collision geometry"):
        Localizer(arm, {"hand": box}, links=["hand", "forearm"])
    with pytest.raises(InputError, match="unknown ray backend"):
        Localizer(arm, {"hand": box}, links=["hand"], ray="optix")
    loc = Localizer(arm, {"hand": box})  # "subtree": every link with a mesh
    assert loc.links == ("hand",) and loc.sensor_names == ("base_ft",)
    q = torch.zeros(2, arm.nv, dtype=torch.float64)
    with pytest.raises(InputError, match="missing readings"):
        loc.localize(q, q, q, {})
    with pytest.raises(InputError, match=r"ft\['base_ft'\] must be"):
        loc.localize(q, q, q, {"base_ft": torch.zeros(3, 6, dtype=torch.float64)})
    with pytest.raises(InputError, match="dtype"):
        loc.localize(q, q, q, {"base_ft": torch.zeros(2, 6)})


def test_near_miss_snaps_to_the_nearest_edge_and_cone_fallback(arm):
    c = np.array([0.3, 0.1, 0.5])
    box = {"hand": _box(arm, "hand", c)}
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    # a vertical push 1 mm beside the +x face (as noise near the silhouette makes it)
    beside = _hand_point(arm, [c + [0.051, 0.01, 0.05]])
    # a push 60 degrees from the top face's normal: outside a 45-degree friction cone
    top = _hand_point(arm, [c + [0.0, 0.01, 0.05]])
    f = torch.tensor([[0, 0, -5.0], [5 * np.sin(1.05), 0, -5 * np.cos(1.05)]]) @ R
    q, ft = _readings(arm, "hand", torch.cat([beside, top]), f)
    r = Localizer(arm, box, links=["hand"]).localize(q, q, q, ft)["base_ft"]
    assert r.status.tolist() == [128, 64] and r.link.tolist() == [0, 0]
    edge = _hand_point(arm, [c + [0.05, 0.01, 0.05]])  # the top face's +x edge
    torch.testing.assert_close(r.position, torch.cat([edge, top]), atol=1e-9, rtol=0)
    r = Localizer(arm, box, links=["hand"], snap_distance=0.0, friction=None).localize(q, q, q, ft)[
        "base_ft"
    ]
    assert r.status.tolist() == [4, 0]
    r = Localizer(arm, box, links=["hand"], snap_distance=5e-4).localize(q, q, q, ft)["base_ft"]
    assert r.status.tolist() == [4, 64]


def test_single_link_onnx_graph_matches_the_localizer(arm):
    ort = pytest.importorskip("onnxruntime")
    from torchcontact.onnx.step.localize import onnx_single_link

    v, f = _l_prism()
    c = np.array([0.3, 0.1, 0.5])
    mesh = _world_mesh(arm, "hand", v + c, f)
    loc = Localizer(arm, {"hand": mesh}, links=["hand"], ray="torch", friction=None)
    rng = np.random.default_rng(0)
    n = 30
    Rr = torch.as_tensor(np.linalg.qr(rng.normal(size=(3, 3)))[0])
    Rr = Rr * torch.det(Rr)
    pr = torch.tensor([0.2, -0.1, 0.6], dtype=torch.float64)
    # pushes at points of the mesh (link frame), some pulling, as wrenches in the sensor frame
    tri = mesh.vertices[mesh.faces]
    k = rng.integers(len(tri), size=n)
    pts = np.einsum("nk,nki->ni", rng.dirichlet([1, 1, 1], size=n), tri[k])
    nrm = np.cross(tri[k, 1] - tri[k, 0], tri[k, 2] - tri[k, 0])
    fl = -(nrm / np.linalg.norm(nrm, axis=1, keepdims=True) + 0.4 * rng.normal(size=(n, 3))) * 5
    fl[::4] = rng.normal(size=fl[::4].shape) * 5  # and some random lines
    ps = torch.as_tensor(pts) @ Rr.T + pr
    fs = torch.as_tensor(fl) @ Rr.T
    W = torch.cat([fs, torch.linalg.cross(ps, fs)], -1)
    W[0] = 0.1  # below the threshold
    far = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64) @ Rr.T + pr  # misses the prism
    W[1] = torch.cat([fs[1], torch.linalg.cross(far, fs[1])])
    ref = loc.localize_wrench(W, Rr.expand(n, 1, 3, 3), pr.expand(n, 1, 3), "base_ft")
    sess = ort.InferenceSession(onnx_single_link(mesh).SerializeToString(),
                                providers=["CPUExecutionProvider"])  # fmt: skip
    status = []
    for i in range(n):
        feeds = {"wrench": W[i].float().numpy(), "R_sensor_link": Rr.float().numpy(),
                 "p_sensor_link": pr.float().numpy()}  # fmt: skip
        pos, nrm, force, mres, st = sess.run(None, feeds)
        status.append(int(st[0]))
        if ref.link[i] >= 0:  # the first entry, as the localizer reports it
            np.testing.assert_allclose(pos, ref.position[i].numpy(), atol=1e-5)
            np.testing.assert_allclose(force, ref.force[i].numpy(), atol=1e-4)
        else:
            assert np.isnan(pos).all()
        assert abs(mres[0] - ref.moment_residual[i].item()) < 1e-4
    assert status == [s & ~16 for s in ref.status.tolist()]  # the graph does not count entries
    assert status[0] == 2 and 0 in status and 4 in status


def _temporal_prior_loop(status, link, pos, starts):
    """The temporal prior frame by frame (the reference of the vectorised one)."""
    n = len(status)
    in_run = [(c & (1 | 2 | 32)) == 0 for c in status]
    runs, k = [], 0
    while k < n:  # maximal runs of contact, cut at segment starts
        if not in_run[k]:
            k += 1
            continue
        j = k + 1
        while j < n and in_run[j] and not starts[j]:
            j += 1
        runs.append(range(k, j))
        k = j
    out_l, out_p = [-1] * n, [[np.nan] * 3 for _ in range(n)]
    for run in runs:
        anchors = [i for i in run if status[i] == 0 and link[i] >= 0]
        if not anchors:
            continue
        votes = np.bincount([link[i] for i in anchors])
        if 3 * votes.max() < 2 * len(anchors):
            continue
        anchors = [i for i in anchors if link[i] == int(np.argmax(votes))]
        for i in run:
            if status[i] & 16:
                j = min(anchors, key=lambda a: (abs(a - i), a))  # the earlier one on a tie
                out_l[i], out_p[i] = link[j], list(pos[j])
    return out_l, out_p


def test_temporal_prior_matches_a_loop_over_frames():
    from torchcontact.localize import temporal_prior

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 300):
        status = rng.choice([0, 0, 0, 16, 16, 2, 64, 32, 1, 16 | 64], n)
        link = np.where(np.isin(status, [0, 16, 64, 80]), rng.integers(0, 3, n), -1)
        pos = rng.normal(size=(n, 3))
        starts = rng.random(n) < 0.05
        pl, pp = temporal_prior(torch.as_tensor(status), torch.as_tensor(link),
                                torch.as_tensor(pos), torch.as_tensor(starts))  # fmt: skip
        rl, rp = _temporal_prior_loop(status.tolist(), link.tolist(), pos, starts.tolist())
        assert pl.tolist() == rl
        np.testing.assert_array_equal(pp.numpy(), np.array(rp).reshape(n, 3))
        assert n < 300 or (pl >= 0).sum() > 20  # the case is exercised


def test_prior_and_sequence_resolve_two_links_on_the_line(arm):
    """Pushing up into the hand's bottom face: a vertical line enters the forearm box below it
    first (ambiguous); a slanted one misses the forearm (the hand only). A prior, or the
    slanted frames before in the same run, pick the hand."""
    ca, cb = np.array([0.3, 0.1, 0.5]), np.array([0.3, 0.1, 0.8])
    meshes = {"forearm": _box(arm, "forearm", ca), "hand": _box(arm, "hand", cb)}
    loc = Localizer(arm, meshes, links=["forearm", "hand"])
    fp = arm.forward_pass(*(torch.zeros(1, arm.nv, dtype=torch.float64),) * 3)
    R = arm.frame_pose(fp, "hand")[0][0]
    hand = loc.links.index("hand")
    p = _hand_point(arm, [cb + [0.04, 0.0, -0.05]])
    up, slant = [0.0, 0.0, 4.0], [-1.2, 0.0, 4.0]
    none = [0.0, 0.0, 0.0]
    kinds = [slant, slant, up, up, up, none, up, up, up, none, slant, up, up]
    f = torch.tensor(kinds, dtype=torch.float64) @ R
    q, ft = _readings(arm, "hand", p.expand(len(kinds), 3), f)
    r = loc.localize(q, q, q, ft)["base_ft"]
    assert r.status.tolist() == [0, 0, 16, 16, 16, 2, 16, 16, 16, 2, 0, 16, 16]
    assert [loc.links[i] for i in r.link[2:5].tolist()] == ["forearm"] * 3
    # a prior on the hand (one on the forearm) takes that link's entry, bit 256 for 16
    n = len(kinds)
    for want in ("hand", "forearm"):
        li = loc.links.index(want)
        prior = (torch.full((n,), li), r.position[2].expand(n, 3) if want == "forearm"
                 else p.expand(n, 3))  # fmt: skip
        rp = loc.localize(q, q, q, ft, prior={"base_ft": prior})["base_ft"]
        amb = r.status == 16
        assert (rp.status[amb] == 256).all() and (rp.link[amb] == li).all()
        assert (rp.status[~amb] == r.status[~amb]).all()
    rp = loc.localize(q, q, q, ft, prior={"base_ft": (torch.full((n,), -1), p.expand(n, 3))})
    assert rp["base_ft"].status.tolist() == r.status.tolist()
    # the sequence: frames 2-4 follow frames 0-1 (run 0-4); frames 6-8 have no unambiguous
    # frame in their run (frames 5 and 9 have no force; the robot is at rest, so both entries
    # stay put and the run stays ambiguous); frame 11 follows 10, a segment starts at 12
    starts = torch.zeros(n, dtype=torch.bool)
    starts[12] = True
    rs = loc.localize_sequence(q, q, q, ft, starts=starts)["base_ft"]
    assert rs.status.tolist() == [0, 0, 256, 256, 256, 2, 16, 16, 16, 2, 0, 256, 16]
    assert (rs.link[[2, 3, 4, 11]] == hand).all()
    torch.testing.assert_close(rs.position[[2, 3, 4, 11]], p.expand(4, 3), atol=1e-9, rtol=0)
    # the log chunk function: the same, and a skin contact in the region ends a run
    from torchcontact.contacts import ContactRecords
    from torchcontact.localize import localize_chunk

    npy = [x.numpy() for x in (q, q, q)]
    skin = ContactRecords([1], ["hand"], ["force"], np.zeros((1, 3)))
    for temporal, want in ((False, r.status.tolist()), (True, rs.status.tolist())):
        lc = localize_chunk(loc, *npy, {"base_ft": ft["base_ft"].numpy()}, ContactRecords.empty(),
                            starts=starts.numpy(), temporal=temporal)  # fmt: skip
        assert lc.columns["localize_status_code.base_ft"].to_pylist() == want
        assert (lc.records.frame == np.flatnonzero(np.isin(want, [0, 256]))).all()
    lc = localize_chunk(loc, *npy, {"base_ft": ft["base_ft"].numpy()}, skin,
                        starts=starts.numpy(), temporal=True)  # fmt: skip
    code = lc.columns["localize_status_code.base_ft"].to_pylist()
    assert code[:5] == [0, 32, 16, 16, 16]  # frame 1 has skin: frames 2-4 follow frame 0 no more
    # holding the contact: a line 4 mm beside the hand point misses the hand and enters only
    # the forearm below (status 0 there); within hold_distance of the run's prior it is held
    p2 = _hand_point(arm, [cb + [0.048, 0.0, -0.05]] * 3 + [cb + [0.052, 0.0, -0.05]])
    f2 = torch.tensor([slant] * 3 + [[0.2, 0.0, 4.0]], dtype=torch.float64) @ R
    q2, ft2 = _readings(arm, "hand", p2, f2)
    for hold, want in ((0.0, ([0, 0, 0, 0], "forearm")), (5e-3, ([0, 0, 0, 256], "hand"))):
        r2 = loc.localize_sequence(q2, q2, q2, ft2, hold_distance=hold)["base_ft"]
        assert r2.status.tolist() == want[0] and loc.links[int(r2.link[3])] == want[1]
    torch.testing.assert_close(r2.position[3], p2[0], atol=1e-9, rtol=0)
    torch.testing.assert_close(r2.normal[3], r2.normal[0])
    empty = loc.localize_sequence(q[:0], q[:0], q[:0], {"base_ft": ft["base_ft"][:0]})
    assert empty["base_ft"].status.shape == (0,) and empty["base_ft"].position.shape == (0, 3)
    with pytest.raises(InputError, match="starts"):
        loc.localize_sequence(q, q, q, ft, starts=starts[:3])
    with pytest.raises(InputError, match="prior"):
        loc.localize(q, q, q, ft, prior={"base_ft": (torch.zeros(2), p)})
