"""Payloads (torchcontact.online.payload): physical checks, parameters, identification."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import torchcontact as tc
from torchcontact.errors import InputError
from torchcontact.online.payload import (
    PARAM_NAMES,
    NotIdentifiableError,
    Payload,
    PayloadIdentifier,
)
from torchcontact.residual import PARAM_NAMES as RESIDUAL_PARAMS
from torchcontact.residual import sensor_regressor


def test_param_names_are_the_regressors():
    assert PARAM_NAMES == RESIDUAL_PARAMS


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(mass=0.0), "mass must be > 0"),
        (dict(mass=float("nan")), "mass must be > 0"),
        (dict(mass=1.0, com=(0, 0)), "com"),
        (dict(mass=1.0, inertia=np.diag([0.1, 0.1, -0.01])), "not positive definite"),
        (dict(mass=1.0, inertia=np.diag([0.1, 0.02, 0.02])), "triangle inequality"),
        (dict(mass=1.0, inertia=[[0.1, 0.01, 0], [0.0, 0.1, 0], [0, 0, 0.1]]), "symmetric"),
    ],
)
def test_non_physical_payloads_are_refused(kw, match):
    with pytest.raises(InputError, match=match):
        Payload(**kw)


def test_params_match_the_model_with_the_payload(arm):
    """Y theta of a payload equals the reading change of the model that carries it (pinocchio's
    combination of inertias is tested for with_point_mass; here with an inertia too)."""
    fr = arm.frame("hand")
    p = Payload(0.7, com=(0.01, -0.02, 0.06), inertia=np.diag([2e-3, 3e-3, 4e-3]), link="hand")
    theta = p.params(fr.R_body_frame, fr.p_body_frame)
    from torchcontact.spatial import combine_inertias

    b = fr.body
    c = fr.R_body_frame @ p.com + fr.p_body_frame
    m1, c1, I1 = combine_inertias(
        [(float(arm.mass[b]), arm.com[b].numpy(), arm.inertia_com[b].numpy()),
         (p.mass, c, fr.R_body_frame @ p.inertia @ fr.R_body_frame.T)]
    )  # fmt: skip
    mass, com, inertia = arm.mass.clone(), arm.com.clone(), arm.inertia_com.clone()
    mass[b], com[b], inertia[b] = m1, torch.as_tensor(c1), torch.as_tensor(I1)
    heavy = dataclasses.replace(arm, mass=mass, com=com, inertia_com=inertia)
    q = torch.rand(5, arm.nv, dtype=torch.float64)
    none = tc.Contacts((), (), q.new_zeros(5, 0, 3))
    d = (tc.ContactEstimator(heavy).predict_ft(q, q, q, none)["base_ft"]
         - tc.ContactEstimator(arm).predict_ft(q, q, q, none)["base_ft"])  # fmt: skip
    Y = sensor_regressor(arm, "base_ft", q, q, q, [b])
    assert torch.allclose(Y @ torch.as_tensor(theta), d, atol=1e-12, rtol=0)
    back = Payload.from_params(theta, fr.R_body_frame, fr.p_body_frame)
    assert back.mass == pytest.approx(0.7) and np.allclose(back.com, p.com)
    assert np.allclose(back.inertia, p.inertia, atol=1e-14)


def _gravity_frames(rng, n, rotate=True):
    """Regressors of a static payload with gravity in random (or one) sensor direction(s)."""
    Ys = []
    for _ in range(n):
        g = rng.normal(size=3) if rotate else np.array([0.0, 0.0, 1.0])
        g *= 9.81 / np.linalg.norm(g)
        Y = np.zeros((6, 10))
        Y[:3, 0] = g
        Y[3:, 1:4] = -np.array([[0, -g[2], g[1]], [g[2], 0, -g[0]], [-g[1], g[0], 0]])
        Ys.append(Y)
    return np.array(Ys)


def test_identification_refuses_without_excitation_then_answers():
    rng = np.random.default_rng(1)
    truth = Payload(0.5, com=(0.02, 0.0, 0.08))
    theta = truth.params()
    offset = np.array([1.0, -2.0, 0.5, 0.1, 0.0, -0.1])
    ident = PayloadIdentifier(ft_std=[0.05] * 3 + [0.005] * 3)
    with pytest.raises(NotIdentifiableError, match="no contact-free frames"):
        ident.identify()
    Y = _gravity_frames(rng, 200, rotate=False)  # the sensor never turns: m and fz offset mix
    ident.update(Y, Y @ theta + offset + rng.normal(size=(200, 6)) * 0.01)
    with pytest.raises(NotIdentifiableError, match="singular|not identified"):
        ident.identify()
    Y = _gravity_frames(rng, 200)
    use = np.ones(200, bool)
    use[:50] = False  # frames in contact are not used
    z = Y @ theta + offset + rng.normal(size=(200, 6)) * np.array([0.05] * 3 + [0.005] * 3)
    z[:50] += 30.0
    ident.update(Y, z, use)
    p = ident.identify()
    est = ident.estimate()
    assert p.mass == pytest.approx(0.5, abs=4 * est.mass_std)
    assert np.allclose(p.com, truth.com, atol=5 * est.com_std.max())
    assert np.allclose(est.offset, offset, atol=0.05)
    assert est.frames == 350


def test_identifier_bad_input():
    with pytest.raises(InputError, match="params"):
        PayloadIdentifier("inertia")
    with pytest.raises(InputError, match="forgetting"):
        PayloadIdentifier(forgetting=0.0)
    with pytest.raises(InputError, match=r"\(N, 6, 10\)"):
        PayloadIdentifier().update(np.zeros((6, 9)), np.zeros(6))
