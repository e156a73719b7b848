"""Contact records <-> slots (the variable-count-to-slots assignment) and the contact-spec parser."""

import json

import numpy as np
import pytest
import torch

import torchcontact as tc
from torchcontact.contacts import (
    ContactRecords,
    Contacts,
    SlotLayout,
    load_contact_spec,
    parse_contact_spec,
)
from torchcontact.errors import InputError


def _records():
    # frame 0: two hand forces and an arm force; frame 1: nothing; frame 2: one hand force
    return ContactRecords(
        frame=[0, 0, 0, 2],
        links=["hand_skin", "forearm_skin", "hand_skin", "hand_skin"],
        kinds=["force"] * 4,
        positions=np.arange(12.0).reshape(4, 3) * 0.01,
    )


def test_slots_cover_the_most_records_of_each_pair_in_a_frame():
    rec = _records()
    layout = SlotLayout.covering(rec)
    assert layout.links == ("forearm_skin", "hand_skin", "hand_skin")
    assert layout.assign(rec).tolist() == [1, 0, 2, 1]  # r-th record of a pair -> r-th slot
    c, slot = Contacts.from_records(rec, 3)
    assert c.positions.shape == (3, 3, 3) and slot.tolist() == [1, 0, 2, 1]
    assert c.active.tolist() == [[True, True, True], [False] * 3, [False, True, False]]
    np.testing.assert_array_equal(c.positions[0, 2].numpy(), rec.positions[2])
    back = c.to_records()
    assert back.frame.tolist() == [0, 0, 0, 2]
    assert sorted(zip(back.links, back.positions[:, 0], strict=True)) == sorted(
        zip(rec.links, rec.positions[:, 0], strict=True)
    )


def test_fixed_layout_leaves_out_what_does_not_fit():
    layout = SlotLayout(("hand_skin",), ("force",))  # e.g. an exported graph's slots
    arrays, slot = layout.fill(_records(), 3)
    assert slot.tolist() == [0, -1, -1, 0]  # the arm force and the second hand force: no slot
    assert arrays["active"].tolist() == [[True], [False], [True]]
    with pytest.raises(InputError, match=r"frames must lie in \[0, 2\)"):
        layout.fill(_records(), 2)


def test_estimate_from_records_equals_the_slot_contacts():
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    est = tc.ContactEstimator(model)
    g = torch.Generator().manual_seed(0)
    q = torch.rand(3, model.nv, generator=g, dtype=torch.float64)
    rec = ContactRecords([0, 1, 2], ["hand_skin", "forearm_skin", "hand_skin"], ["force"] * 3,
                         np.zeros((3, 3)))  # fmt: skip
    push = torch.tensor([[0.0, 0.0, -10.0, 0, 0, 0]], dtype=torch.float64)
    truth = Contacts(["hand_skin", "forearm_skin"], ["known"] * 2, torch.zeros(3, 2, 3,
                     dtype=torch.float64), wrenches=push.expand(3, 2, 6).clone(),
                     active=torch.tensor([[True, False], [False, True], [True, False]]))  # fmt: skip
    ft = est.predict_ft(q, q, q, truth)
    c, slot = Contacts.from_records(rec, 3)
    r = est.estimate(q, q, q, ft, c)
    f = r.force.numpy()[rec.frame, slot]  # back to the records
    np.testing.assert_allclose(f, [[0, 0, -10]] * 3, atol=1e-9)


SPEC_TOML = """
[[contact]]
link = "hand_skin"
position = [0.0, 0.0, 0.01]

[[contact]]
link = "forearm_skin"
kind = "force_dir"
position = [0, 0, 0]
direction = [0, 0, -1]
start_ns = 10
end_ns = 20
"""


def test_toml_and_json_specs_parse_alike(tmp_path):
    (tmp_path / "s.toml").write_text(SPEC_TOML)
    data = {
        "contact": [
            {"link": "hand_skin", "position": [0.0, 0.0, 0.01]},
            {"link": "forearm_skin", "kind": "force_dir", "position": [0, 0, 0],
             "direction": [0, 0, -1], "start_ns": 10, "end_ns": 20},
        ]
    }  # fmt: skip
    (tmp_path / "s.json").write_text(json.dumps(data))
    a, b = load_contact_spec(tmp_path / "s.toml"), load_contact_spec(tmp_path / "s.json")
    for x in (a, b):
        assert x.entries.links.tolist() == ["hand_skin", "forearm_skin"]
        assert x.entries.kinds.tolist() == ["force", "force_dir"] and x.timed
    rec = a.at(np.array([0, 10, 15, 30]))
    assert rec.frame.tolist() == [0, 1, 1, 2, 2, 3] and rec.links[2] == "forearm_skin"
    np.testing.assert_array_equal(rec.directions[2], [0, 0, -1])
    with pytest.raises(InputError, match="start_ns/end_ns apply to logs only"):
        a.static()
    static = parse_contact_spec(data["contact"][:1]).static()
    assert static.frame.tolist() == [0]


@pytest.mark.parametrize(
    "entry,match",
    [
        ({"link": "a"}, "contact 0 needs 'position'"),
        ({"link": "a", "position": [0, 0]}, "position must be a list of 3 finite numbers"),
        ({"link": "a", "position": [0, 0, 0], "kind": "push"}, "unknown kind 'push'"),
        ({"link": "a", "position": [0, 0, 0], "kind": "known"}, "a known contact needs a wrench"),
        ({"link": "a", "position": [0, 0, 0], "colour": 1}, r"unknown keys \['colour'\]"),
        ({"link": "a", "position": [0, 0, 0], "start_ns": 5, "end_ns": 1}, "is after end_ns"),
        ({"link": "a", "position": [0, 0, float("nan")]}, "finite numbers"),
    ],
)
def test_spec_errors_name_the_entry(entry, match):
    with pytest.raises(InputError, match=match):
        parse_contact_spec({"contact": [entry]}, "spec.toml")


def test_spec_file_errors(tmp_path):
    with pytest.raises(InputError, match="cannot read the contact spec"):
        load_contact_spec(tmp_path / "none.toml")
    (tmp_path / "bad.toml").write_text("[[contact]\nlink =")
    with pytest.raises(InputError, match="not a valid TOML contact spec"):
        load_contact_spec(tmp_path / "bad.toml")
    (tmp_path / "old.json").write_text('{"positions": [[0, 0, 0]], "active": [1]}')
    with pytest.raises(InputError, match=r"unknown top-level keys \['active', 'positions'\]"):
        load_contact_spec(tmp_path / "old.json")
