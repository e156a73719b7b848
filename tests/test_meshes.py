"""Robot geometry: URDF visual/collision elements loaded into body frames, checked against pinocchio.

pinocchio's ``buildGeomFromUrdf`` gives every geometry object's placement in its parent joint
frame, which is torchcontact's body frame; the mesh files are read raw with trimesh and placed with
pinocchio's placements, and the axis-aligned bounds per link must agree with ours.
"""

from __future__ import annotations

import numpy as np
import pytest
from robots import ROBOTS

import torchcontact as tc
from torchcontact.errors import InputError
from torchcontact.meshes import load_meshes, resolve_uri

trimesh = pytest.importorskip("trimesh")


def _pin_bounds(path, links, kind="collision"):
    """Per link: (min, max) of its geometry placed by pinocchio, in the parent joint frame."""
    import pinocchio as pin

    m = pin.buildModelFromUrdf(str(path))
    gtype = pin.COLLISION if kind == "collision" else pin.VISUAL
    g = pin.buildGeomFromUrdf(m, str(path), gtype, package_dirs=[str(p) for p in path.parents])
    out = {}
    for o in g.geometryObjects:
        link = m.frames[o.parentFrame].name
        if link not in links:
            continue
        if o.meshPath and o.meshPath != "BOX":
            v = np.asarray(trimesh.load(o.meshPath, force="mesh", process=False).vertices)
            v = v * np.asarray(o.meshScale)
        else:  # a box: hppfcl keeps half sides
            h = np.asarray(o.geometry.halfSide)
            v = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
        R, p = o.placement.rotation, o.placement.translation
        w = v @ R.T + p
        lo, hi = out.get(link, (np.full(3, np.inf), np.full(3, -np.inf)))
        out[link] = (np.minimum(lo, w.min(0)), np.maximum(hi, w.max(0)))
    return out


@pytest.mark.parametrize(
    "robot, links",
    [
        ("panda", ("panda_link0", "panda_link4", "panda_hand", "panda_leftfinger")),
        ("icub", ("l_forearm", "l_hand", "chest")),
    ],
)
def test_collision_meshes_in_body_frames_match_pinocchio(robot, links):
    path = ROBOTS[robot]()
    model = tc.RobotModel.from_urdf(path)
    meshes = load_meshes(model, path, "collision", links=links)
    assert meshes.missing == ()
    ref = _pin_bounds(path, links)
    assert set(meshes.links) == set(ref) == set(links)
    for link, lm in meshes.links.items():
        v = lm.vertices_in_body()
        np.testing.assert_allclose(v.min(0), ref[link][0], atol=1e-9, err_msg=link)
        np.testing.assert_allclose(v.max(0), ref[link][1], atol=1e-9, err_msg=link)
        assert lm.faces.min() >= 0 and lm.faces.max() < len(lm.vertices)
        assert lm.body == model.frame(link).body
    # panda_hand is merged into panda_link7's body across its fixed joint: not the identity there
    if robot == "panda":
        hand = meshes.links["panda_hand"]
        assert hand.body == model.body_of("panda_link7")
        assert not np.allclose(hand.vertices_in_body(), hand.vertices)


def test_primitives_origins_scale_and_colours(tmp_path):
    (tmp_path / "m").mkdir()
    tri = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]])
    tri.export(tmp_path / "m" / "tri.stl")
    urdf = tmp_path / "r.urdf"
    urdf.write_text(
        """<robot name="r">
  <material name="red"><color rgba="1 0 0 1"/></material>
  <link name="base">
    <visual><origin xyz="0 0 1"/><geometry><box size="0.2 0.4 0.6"/></geometry>
      <material name="red"/></visual>
    <visual><geometry><mesh filename="m/tri.stl" scale="2 2 2"/></geometry></visual>
    <collision><origin xyz="1 0 0" rpy="0 0 1.5707963267948966"/>
      <geometry><cylinder radius="0.1" length="0.5"/></geometry></collision>
    <collision><geometry><sphere radius="0.3"/></geometry></collision>
    <collision><geometry><mesh filename="package://nowhere/x.stl"/></geometry></collision>
  </link>
</robot>"""
    )
    model = tc.RobotModel.from_urdf(urdf)
    vis = load_meshes(model, urdf, "visual")
    v = vis.links["base"].vertices
    box, tri2 = v[:8], v[8:]
    np.testing.assert_allclose(box.min(0), [-0.1, -0.2, 0.7], atol=1e-12)
    np.testing.assert_allclose(box.max(0), [0.1, 0.2, 1.3], atol=1e-12)
    np.testing.assert_allclose(tri2.max(0), [2, 2, 0], atol=1e-6)  # scaled mesh (float32 STL)
    colours = vis.links["base"].vertex_colors
    assert colours.shape == (len(v), 4) and (colours[:8] == [255, 0, 0, 255]).all()
    col = load_meshes(model, urdf, "collision")
    c = col.links["base"].vertices
    assert c[:, 0].max() == pytest.approx(1.1, abs=1e-3)  # cylinder axis z, turned about z
    assert c[:, 2].max() == pytest.approx(0.3, abs=1e-3)  # sphere radius
    assert [(m[0], m[1]) for m in col.missing] == [("base", "package://nowhere/x.stl")]
    assert "nowhere" in col.missing[0][2]


def test_resolve_uri_rules_and_errors(tmp_path):
    urdf = ROBOTS["icub"]()
    p = resolve_uri("package://iCub/meshes/simmechanics/sim_sea_2-5_l_hand_prt-binary.stl", urdf)
    assert p.is_file() and p.name.endswith("l_hand_prt-binary.stl")
    (tmp_path / "pkgs" / "mypkg").mkdir(parents=True)
    (tmp_path / "pkgs" / "mypkg" / "a.stl").write_text("solid")
    u = tmp_path / "x.urdf"
    assert (
        resolve_uri("package://mypkg/a.stl", u, [tmp_path / "pkgs"])
        == tmp_path / "pkgs" / "mypkg" / "a.stl"
    )
    assert resolve_uri("pkgs/mypkg/a.stl", u) == tmp_path / "pkgs" / "mypkg" / "a.stl"
    with pytest.raises(FileNotFoundError, match="package 'other' not found"):
        resolve_uri("package://other/a.stl", u)
    with pytest.raises(FileNotFoundError, match="no such file"):
        resolve_uri("file://missing.stl", u)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    with pytest.raises(InputError, match="no_such_link"):
        load_meshes(model, tc.robots.tcarm_path(), links=["no_such_link"])
    with pytest.raises(InputError, match="kind"):
        load_meshes(model, tc.robots.tcarm_path(), kind="both")
