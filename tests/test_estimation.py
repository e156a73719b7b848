"""Contact estimator: round trips on the bundled arm, chunking, layout errors.

Reference comparisons against iDynTree and pinocchio live in test_estimation_idyntree.py.
"""

from __future__ import annotations

import pytest
import torch

import torchcontact as tc

F64 = torch.float64


@pytest.fixture(scope="module")
def arm():
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path())


def _state(model, n, seed):
    g = torch.Generator().manual_seed(seed)
    return tuple((torch.rand(n, model.nv, generator=g, dtype=F64) * 2 - 1) for _ in range(3))


def test_round_trip_one_wrench_on_the_hand(arm):
    est = tc.ContactEstimator(arm)
    q, qd, qdd = _state(arm, 50, 0)
    g = torch.Generator().manual_seed(1)
    pos = torch.randn(50, 1, 3, generator=g, dtype=F64) * 0.03
    w = torch.randn(50, 1, 6, generator=g, dtype=F64) * 5
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(("hand_skin",), ("known",), pos, wrenches=w))
    r = est.estimate(q, qd, qdd, ft, tc.Contacts(("hand_skin",), ("wrench",), pos))
    torch.testing.assert_close(torch.cat((r.force, r.moment), -1), w, atol=1e-9, rtol=0)
    assert (r.rank["base_ft"] == 6).all() and r.identifiable["base_ft"].all()
    assert (r.residual["base_ft"] < 1e-9).all() and (r.status == 0).all()


def test_no_contact_residual_is_the_reading_mismatch(arm):
    est = tc.ContactEstimator(arm)
    q, qd, qdd = _state(arm, 20, 2)
    empty = tc.Contacts((), (), torch.zeros(20, 0, 3, dtype=F64))
    ft = est.predict_ft(q, qd, qdd, empty)["base_ft"]
    offset = torch.tensor([1.0, 0, 0, 0, 0, 0], dtype=F64)
    r = est.estimate(q, qd, qdd, {"base_ft": ft + offset}, empty)
    assert (r.unknowns["base_ft"] == 0).all() and (r.rank["base_ft"] == 0).all()
    torch.testing.assert_close(r.residual["base_ft"], torch.ones(20, dtype=F64), atol=1e-9, rtol=0)
    assert r.force.shape == (20, 0, 3)


def test_chunked_equals_one_go(arm):
    est = tc.ContactEstimator(arm)
    q, qd, qdd = _state(arm, 1000, 3)
    g = torch.Generator().manual_seed(4)
    pos = torch.randn(1000, 2, 3, generator=g, dtype=F64) * 0.03
    active = torch.rand(1000, 2, generator=g) < 0.6
    ft = {"base_ft": torch.randn(1000, 6, generator=g, dtype=F64)}
    c = tc.Contacts(("forearm_skin", "hand_skin"), ("force", "force"), pos, active=active)
    a = est.estimate(q, qd, qdd, ft, c, chunk_size=None)
    b = est.estimate(q, qd, qdd, ft, c, chunk_size=128)
    for x, y in zip(a, b, strict=True):
        if isinstance(x, dict):
            for k in x:
                torch.testing.assert_close(x[k], y[k], atol=1e-12, rtol=0)
        elif x is not None:
            torch.testing.assert_close(x, y, atol=1e-12, rtol=0)


def test_layout_errors(arm):
    est = tc.ContactEstimator(arm)
    q, qd, qdd = _state(arm, 2, 5)
    ft = {"base_ft": torch.zeros(2, 6, dtype=F64)}
    pos = torch.zeros(2, 1, 3, dtype=F64)
    with pytest.raises(ValueError, match="unknown link.*'palm'"):
        est.estimate(q, qd, qdd, ft, tc.Contacts(("palm",), ("force",), pos))
    with pytest.raises(ValueError, match="'base_link' lies outside every F/T sensor"):
        est.estimate(q, qd, qdd, ft, tc.Contacts(("base_link",), ("force",), pos))
    with pytest.raises(ValueError, match="unknown kind 'torque'"):
        tc.Contacts(("hand",), ("torque",), pos)
    with pytest.raises(ValueError, match="missing readings of sensors \\['base_ft'\\]"):
        est.estimate(q, qd, qdd, {}, tc.Contacts(("hand",), ("force",), pos))
    with pytest.raises(ValueError, match="unknown F/T sensors \\['wrist'\\]"):
        tc.ContactEstimator(arm, ["wrist"])
    with pytest.raises(ValueError, match=r"contacts.positions must have shape \(\*B, 1, 3\)"):
        est.estimate(
            q, qd, qdd, ft, tc.Contacts(("hand",), ("force",), torch.zeros(2, 2, 3, dtype=F64))
        )
