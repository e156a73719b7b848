import numpy as np
import pytest

import torchcontact as tc
from torchcontact.simulation import UnmodeledEffects, _with_payload, simulate
from training.baselines import (
    InertialLeastSquares,
    inertial_params,
    inertial_regressor,
    predict_free,
    subtree_bodies,
    with_inertial_params,
)


@pytest.fixture(scope="module")
def log(arm):
    return simulate(arm, 300, seed=3)


def test_regressor_times_true_params_is_predict_ft(arm, log):
    Y = inertial_regressor(arm, "base_ft", log.q, log.qd, log.qdd, chunk=128)  # chunking too
    bodies = subtree_bodies(arm, "base_ft")
    assert Y.shape == (300, 6, 10 * len(bodies))
    for model in (arm, _with_payload(arm, "hand", 0.7, (0.02, -0.01, 0.08))):
        pred = predict_free(
            tc.ContactEstimator(model, ["base_ft"]), log.q, log.qd, log.qdd, "base_ft"
        )
        got = Y @ inertial_params(model, bodies)
        scale = np.abs(pred).max()
        assert scale > 1.0
        np.testing.assert_allclose(got, pred, rtol=0, atol=1e-10 * scale)
    # frames differ (the regressor is not a constant)
    assert not np.allclose(Y[0], Y[1])


def test_param_conversion_round_trip(arm):
    bodies = subtree_bodies(arm, "base_ft")
    th = inertial_params(arm, bodies)
    back = with_inertial_params(arm, bodies, th)
    for f in ("mass", "com", "inertia_com"):
        np.testing.assert_allclose(getattr(back, f).numpy(), getattr(arm, f).numpy(), atol=1e-12)


def test_least_squares_recovers_offset_and_payload(arm):
    fx = UnmodeledEffects(offset=(1.0, -2.0, 3.0, 0.1, 0.2, -0.3), payload_mass=0.5)
    log = simulate(arm, 1500, seed=4, effects=fx)
    free = (log.contact_link < 0).all(1)
    est = tc.ContactEstimator(arm, ["base_ft"])
    r = log.ft - predict_free(est, log.q, log.qd, log.qdd, "base_ft")
    Y = inertial_regressor(arm, "base_ft", log.q, log.qd, log.qdd)
    ls = InertialLeastSquares().fit(arm, "base_ft", Y[free], r[free])
    after = r[free] - ls.correction(Y[free])
    before = r[free] - r[free].mean(0)
    assert np.abs(before).max() > 0.5  # the payload is visible beyond a constant
    assert np.abs(after).max() < 1e-6  # noiseless: the physics explains it exactly
    # fx, fy offsets are identifiable; fz is not: a mass change with unchanged first moments
    # adds the constant m g to fz on a fixed base, exactly like an fz offset (min-norm split)
    np.testing.assert_allclose(ls.offset[:2], fx.offset[:2], atol=1e-6)
    assert ls.rank < Y.shape[-1] + 6
