"""What every view of a log draws (``torchcontact.logs.plot``'s shared part), and the bundled
arm's visual geometry."""

from __future__ import annotations

import re

import numpy as np
import torch

import torchcontact as tc
from torchcontact.contacts import ContactRecords
from torchcontact.logs.plot import (
    SLOT_COLORS,
    contact_slots,
    ill_posed_note,
    rank_deficient,
    slot_label,
    slot_rgb,
)
from torchcontact.status import STATUS, STATUS_NAMES, status_bits


def test_every_status_bit_has_a_short_name():
    assert set(STATUS_NAMES) == set(STATUS)
    names = list(STATUS_NAMES.values())
    assert len(set(names)) == len(names)
    assert all(re.fullmatch(r"[a-z_]+", n) for n in names)
    assert status_bits(0) == [] and status_bits(2 | 128) == ["joint_nonfinite", "invalid_contact"]


def test_two_contacts_on_one_link_are_two_slots_of_two_colours():
    rec = ContactRecords(
        frame=[0, 0, 1, 2, 2, 2],
        links=["hand", "hand", "hand", "arm", "hand", "hand"],
        kinds=["force"] * 6,
        positions=np.zeros((6, 3)),
    )
    layout, slot = contact_slots(rec)
    assert layout.links == ("arm", "hand", "hand")
    assert slot.tolist() == [1, 2, 1, 0, 1, 2]
    assert slot_rgb(1) != slot_rgb(2) and slot_rgb(1)[:3] == SLOT_COLORS[1]
    assert [slot_label(layout, k) for k in range(3)] == [
        "slot 0: arm",
        "slot 1: hand #1",
        "slot 2: hand #2",
    ]


def test_ill_posed_frames_and_captions():
    rank = {"a": np.array([3, 5, 6]), "b": np.array([1, 1, 0])}
    unknowns = {"a": np.array([3, 6, 6]), "b": np.array([1, 1, 1])}
    assert rank_deficient(rank, unknowns).tolist() == [False, True, True]
    assert "minimum-norm" in ill_posed_note(False)
    assert "minimum-norm" not in ill_posed_note(True) and "constrained" in ill_posed_note(True)


def test_tcarm_visual_geometry_changes_neither_kinematics_nor_inertias():
    path = tc.robots.tcarm_path()
    text = path.read_text()
    assert text.count("<visual>") == 16
    bare = re.sub(r"\s*<visual>.*?</visual>", "", text, flags=re.S)
    bare = re.sub(r"\s*<material name=\"\w+\"><color rgba=\"[\d. ]+\"/></material>", "", bare)
    assert "<visual>" not in bare and "<material" not in bare
    a = tc.RobotModel.from_urdf(path)
    import io

    b = tc.RobotModel.from_urdf(io.StringIO(bare))
    assert a.body_names == b.body_names and a.joint_names == b.joint_names
    assert a.frames.keys() == b.frames.keys() and a.ft_sensors.keys() == b.ft_sensors.keys()
    from torchcontact.model import _TENSOR_FIELDS

    for name in _TENSOR_FIELDS:
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert a.identity.sha256 == b.identity.sha256  # the robot's identity ignores visual geometry
    for f in a.frames:
        np.testing.assert_array_equal(a.frames[f].p_body_frame, b.frames[f].p_body_frame)
        np.testing.assert_array_equal(a.frames[f].R_body_frame, b.frames[f].R_body_frame)
