"""RobotModel construction from URDF: structure, frames, F/T sensors and malformed files."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from robots import load_model

import torchcontact as tc

MINI = """<robot name="mini">
  <link name="base"/>
  <link name="l1"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="tool_joint" type="fixed"><parent link="l1"/><child link="tool"/>
    <origin xyz="0 0 0.5" rpy="0 0 0"/></joint>
</robot>"""


def urdf(text):
    return io.StringIO(text)


def test_icub_structure_frames_and_sensors():
    model = load_model("icub")
    assert model.nv == 32 and len(model.levels) >= 10
    # bodies are sorted by depth and every parent lies in the previous depth's range
    for d, ((s, e), parent) in enumerate(
        zip(model.levels[1:], model.level_parent, strict=True), start=1
    ):
        ps, pe = model.levels[d - 1]
        assert all(ps <= model.body_parent[i] < pe for i in range(s, e))
        assert torch.equal(parent + ps, torch.tensor(model.body_parent[s:e]))
    assert set(model.ft_sensors) == {
        "l_arm_ft",
        "r_arm_ft",
        "l_leg_ft",
        "r_leg_ft",
        "l_foot_ft",
        "r_foot_ft",
    }
    s = model.ft_sensors["l_arm_ft"]
    assert (
        s.joint == "l_arm_ft_sensor"
        and s.frame == "child"
        and s.measure_direction == "child_to_parent"
    )
    assert model.body_joint[s.child_body] == "l_arm_ft_sensor"  # the sensor joint splits two bodies
    assert model.body_parent[s.child_body] == s.parent_body
    # every URDF link and joint is addressable; merged fixed frames keep their own placement
    f = model.frame("l_hand_dh_frame")
    assert model.body_names[f.body] != "l_hand_dh_frame" and np.linalg.norm(f.p_body_frame) > 0
    assert model.frame("l_elbow").body == model.body_joint.index("l_elbow")  # joint = child frame
    total_mass = model.mass.sum().item()
    assert 25 < total_mass < 40  # the whole iCub's links, merged bodies included
    with pytest.raises(KeyError, match="did you mean"):
        model.frame("l_hand_dh_fram")


def test_to_returns_a_copy():
    model = load_model("ur5")
    m32 = model.to(dtype=torch.float32)
    assert m32.dtype == torch.float32 and model.dtype == torch.float64
    assert m32.mass.data_ptr() != model.mass.data_ptr()
    with pytest.raises(ValueError, match="floating"):
        model.to(dtype=torch.int64)


def test_user_declared_sensor_on_a_kept_fixed_joint():
    model = tc.RobotModel.from_urdf(urdf(MINI), keep_fixed=["tool_joint"])
    assert model.nb == 3
    m2 = model.with_ft_sensor(
        "wrist", "tool_joint", frame="child", measure_direction="parent_to_child"
    )
    assert m2.ft_sensors["wrist"].child_body == 2 and "wrist" not in model.ft_sensors
    merged = tc.RobotModel.from_urdf(urdf(MINI))
    assert merged.nb == 2
    with pytest.raises(ValueError, match="keep_fixed"):
        merged.with_ft_sensor("wrist", "tool_joint")
    with pytest.raises(ValueError, match="moving joint"):
        model.with_ft_sensor("x", "j1")


BAD = {
    "no inertial on a moving link": (
        MINI.replace(
            '<inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>',
            "",
        ),
        r"link 'l1' \(child of revolute joint 'j1'\) has no <inertial>",
    ),
    "unknown joint type": (
        MINI.replace('type="revolute"', 'type="screw"'),
        "joint 'j1' has unknown type 'screw'",
    ),
    "missing link": (
        MINI.replace('<child link="tool"/>', '<child link="toool"/>'),
        "joint 'tool_joint' names missing child link 'toool'",
    ),
    "cycle": (
        MINI.replace(
            "</robot>",
            '<joint name="back" type="fixed"><parent link="tool"/><child link="base"/></joint></robot>',
        ),
        "do not form one tree",
    ),
    "two parents": (
        MINI.replace(
            "</robot>",
            '<joint name="again" type="fixed"><parent link="base"/><child link="tool"/></joint></robot>',
        ),
        "link 'tool' is the child of two joints",
    ),
    "malformed xml": (MINI[:-20], "malformed XML"),
    "sensor on a missing joint": (
        MINI.replace(
            "</robot>",
            '<sensor name="s" type="force_torque"><parent joint="nope"/></sensor></robot>',
        ),
        "sensor 's' names missing joint 'nope'",
    ),
    "bad measure direction": (
        MINI.replace(
            "</robot>",
            '<sensor name="s" type="force_torque"><parent joint="tool_joint"/><force_torque><frame>child</frame><measure_direction>up</measure_direction></force_torque></sensor></robot>',
        ),
        "measure_direction",
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_urdf_names_the_element(case):
    text, message = BAD[case]
    with pytest.raises(tc.URDFError, match=message):
        tc.RobotModel.from_urdf(urdf(text))


def test_missing_file():
    with pytest.raises(FileNotFoundError, match="nope.urdf"):
        tc.RobotModel.from_urdf("/nonexistent/nope.urdf")


def test_identity_is_the_parsed_model_not_the_text():
    """Comments, indentation, number spelling and element order keep the identity; every
    number the estimator reads changes it, and the difference is named."""
    a = tc.RobotModel.from_urdf(urdf(MINI))
    reordered = MINI.replace('<link name="tool"/>\n', "").replace(
        "</robot>", '  <link name="tool"/>\n<!-- moved -->\n</robot>'
    )
    b = tc.RobotModel.from_urdf(urdf(reordered.replace('value="1"', 'value="1.0e0"')))
    assert a.urdf_sha256 != b.urdf_sha256 and a.identity.sha256 == b.identity.sha256
    assert a.to(dtype=torch.float32).identity == a.identity
    heavier = tc.RobotModel.from_urdf(
        urdf(MINI.replace('<mass value="1"/>', '<mass value="1.01"/>'))
    )
    assert heavier.identity.sha256 != a.identity.sha256
    assert a.identity.difference(heavier.identity) == "link l1: mass 1 vs 1.01 kg"
    moved = tc.RobotModel.from_urdf(urdf(MINI.replace('xyz="0 0 0.5"', 'xyz="0 0 0.51"')))
    assert a.identity.difference(moved.identity).startswith("joint tool_joint: origin")
    slower = tc.RobotModel.from_urdf(urdf(MINI.replace('velocity="1"', 'velocity="2"')))
    assert a.identity.difference(slower.identity) == "joint j1: velocity limit 1 vs 2 rad/s or m/s"
    # how the model is built from the URDF does not change it; the with_* methods keep it current
    assert tc.RobotModel.from_urdf(urdf(MINI), keep_fixed=["tool_joint"]).identity == a.identity
    heavy = a.with_point_mass("l1", 0.01).identity
    assert a.identity.difference(heavy) == "link l1: added mass 1 absent vs 0.01 0 0 0 kg, m"
    kept = tc.RobotModel.from_urdf(urdf(MINI), keep_fixed=["tool_joint"])
    assert "sensor s" in kept.identity.difference(kept.with_ft_sensor("s", "tool_joint").identity)
