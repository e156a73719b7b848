"""The inertial regressor of a sensor (library) and the physics layers fitted on it (training)."""

import numpy as np
import pytest
import torch
from robots import TOL, load_model

import torchcontact as tc
from torchcontact.residual import (
    PARAM_NAMES,
    body_regressor,
    inertial_params,
    sensor_joints,
    sensor_regressor,
    subtree_bodies,
)
from torchcontact.simulation import UnmodeledEffects, simulate
from training.baselines import RegressorBlocks, fit_inertial, predict_free
from training.data import ResidualDataset, time_blocks

SENSORS = [("tcarm", "base_ft"), ("icub", "l_arm_ft"), ("icub", "r_leg_ft")]


def _model(name):
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path()) if name == "tcarm" else load_model(name)


def test_body_regressor_matches_pinocchio():
    import pinocchio as pin

    rng = np.random.default_rng(0)
    v, a = rng.normal(size=(2, 5, 6))
    Y = body_regressor(torch.as_tensor(v), torch.as_tensor(a)).numpy()
    assert Y.shape == (5, 6, 10) and not np.allclose(Y[0], Y[1])
    for i in range(5):
        ref = pin.bodyRegressor(pin.Motion(v[i]), pin.Motion(a[i]))
        np.testing.assert_allclose(Y[i], ref, **TOL[torch.float64])
        # and the parameter order is pinocchio's dynamic parameters
        inertia = pin.Inertia.Random()
        f = (inertia * pin.Motion(a[i]) + pin.Motion(v[i]).cross(inertia * pin.Motion(v[i]))).vector
        np.testing.assert_allclose(Y[i] @ inertia.toDynamicParameters(), f, atol=1e-9)
    assert PARAM_NAMES[:4] == ("m", "mcx", "mcy", "mcz")


@pytest.mark.parametrize("robot,sensor", SENSORS)
@pytest.mark.parametrize("batch", [(), (1,), (7,), (2, 3)])
def test_regressor_times_params_is_predict_ft(robot, sensor, batch):
    """``Y theta`` is the contact-free reading (predict_ft, itself tested against iDynTree), for
    the nominal model and for one with a payload on the end effector."""
    model = _model(robot)
    g = torch.Generator().manual_seed(1)
    q, qd, qdd = (torch.randn(*batch, model.nv, generator=g, dtype=torch.float64) for _ in range(3))
    Y = sensor_regressor(model, sensor, q, qd, qdd)
    bodies = subtree_bodies(model, sensor)
    assert Y.shape == (*batch, 6, 10 * len(bodies))
    hand = model.body_names[bodies[-1]]
    for m in (model, model.with_point_mass(hand, 0.7, (0.02, -0.01, 0.08))):
        n = int(np.prod(batch))
        nominal = tc.ContactEstimator(m, [sensor]).predict_ft(
            q, qd, qdd, tc.Contacts((), (), q.new_zeros(*batch, 0, 3))
        )[sensor]
        got = Y @ torch.as_tensor(inertial_params(m, bodies))
        scale = float(nominal.abs().max())
        assert scale > 0.1 or n == 0
        torch.testing.assert_close(got, nominal, rtol=0, atol=1e-10 * max(scale, 1.0))
    if batch == (7,):
        assert not torch.allclose(Y[0], Y[1])


def test_sensor_joints_are_exactly_those_that_move_the_reading():
    model = load_model("icub")
    joints = sensor_joints(model, "l_arm_ft")
    assert joints == [
        "torso_pitch", "torso_roll", "torso_yaw", "l_shoulder_pitch", "l_shoulder_roll",
        "l_shoulder_yaw", "l_elbow", "l_wrist_prosup", "l_wrist_pitch", "l_wrist_yaw",
    ]  # fmt: skip
    est = tc.ContactEstimator(model, ["l_arm_ft"])
    g = torch.Generator().manual_seed(2)
    q, qd, qdd = (torch.randn(3, model.nv, generator=g, dtype=torch.float64) for _ in range(3))
    none = tc.Contacts((), (), q.new_zeros(3, 0, 3))
    base = est.predict_ft(q, qd, qdd, none)["l_arm_ft"]
    for i, j in enumerate(model.joint_names):
        q2, qd2 = q.clone(), qd.clone()
        q2[:, i] += 0.7
        qd2[:, i] += 0.9
        moved = est.predict_ft(q2, qd2, qdd, none)["l_arm_ft"]
        changes = not torch.allclose(moved, base, atol=1e-9)
        assert changes == (j in joints), j
    assert sensor_joints(_model("tcarm"), "base_ft") == list(_model("tcarm").joint_names)


def _dataset(model, sensor, frames, seed, effects, **kw):
    log = simulate(model, frames, sensor=sensor, seed=seed, effects=effects, **kw)
    return ResidualDataset.from_simulated(log)


def test_blockwise_qr_equals_the_stacked_least_squares():
    model = _model("tcarm")
    ds = _dataset(
        model, "base_ft", 900, 5, UnmodeledEffects(payload_mass=0.3, noise_std=(0.05,) * 6)
    )
    r = ds.ft - predict_free(model, "base_ft", ds.q, ds.qd, ds.qdd)
    blocks = time_blocks(ds.file_id, 100)
    rb = RegressorBlocks.build(model, ds, r, blocks)
    ids = [0, 2, 3, 7]
    R, c, rr, rows = rb.combine(ids)
    sel = np.concatenate([np.arange(*blocks[i]) for i in ids])
    sel = sel[ds.contact_free[sel]]
    Y = sensor_regressor(
        model, "base_ft", *(torch.as_tensor(x[sel]) for x in (ds.q, ds.qd, ds.qdd))
    )
    A = np.concatenate([np.broadcast_to(np.eye(6), (len(sel), 6, 6)), Y.numpy()], -1)
    A = A.reshape(-1, A.shape[-1])
    b = r[sel].reshape(-1)
    assert rows == len(sel)
    np.testing.assert_allclose(R.T @ R, A.T @ A, rtol=1e-9, atol=1e-8 * np.abs(A.T @ A).max())
    np.testing.assert_allclose(R.T @ c, A.T @ b, rtol=1e-9, atol=1e-8 * np.abs(A.T @ b).max())
    np.testing.assert_allclose(rr, b @ b, rtol=1e-12)


def test_inertial_fit_recovers_a_payload_in_the_identifiable_directions():
    model = _model("tcarm")
    fx = UnmodeledEffects(offset=(1.0, -2.0, 3.0, 0.1, 0.2, -0.3), payload_mass=0.5)
    ds = _dataset(model, "base_ft", 1500, 4, fx)
    r = ds.ft - predict_free(model, "base_ft", ds.q, ds.qd, ds.qdd)
    blocks = time_blocks(ds.file_id, 150)
    rb = RegressorBlocks.build(model, ds, r, blocks)
    fit = fit_inertial(rb, range(len(blocks) - 2), [len(blocks) - 2, len(blocks) - 1])
    free = ds.contact_free
    t = [torch.as_tensor(x[free]) for x in (ds.q, ds.qd, ds.qdd)]
    Y = sensor_regressor(model, "base_ft", *t).numpy()
    after = r[free] - (Y @ fit.delta + fit.offset)
    assert np.abs(r[free] - r[free].mean(0)).max() > 0.5  # the payload is more than an offset
    assert np.abs(after).max() < 1e-6  # noiseless: the physics explains it exactly
    # fx, fy offsets are identifiable; an fz offset is not (on a fixed base a mass with unchanged
    # first moments adds a constant m g to fz): fewer directions than unknowns, and fz is split
    np.testing.assert_allclose(fit.offset[:2], fx.offset[:2], atol=1e-6)
    assert fit.rank <= fit.identifiable < fit.columns
    assert fit.val_rms[fit.rank] <= fit.val_rms.min() + 1e-12


def test_unexcited_directions_are_never_fitted():
    """Only one joint moves: most parameter combinations are invisible. The fit leaves them at
    the URDF values (its change is orthogonal to the unexcited directions), whatever the noise."""
    model = _model("tcarm")
    log = simulate(model, 1200, seed=6, effects=UnmodeledEffects(noise_std=(0.2,) * 6))
    log.q[:, 1:] = 0.3
    log.qd[:, 1:] = 0.0
    log.qdd[:, 1:] = 0.0
    ds = ResidualDataset.from_simulated(log)
    ds.contact_free[:] = True
    ds.ft[:] = predict_free(model, "base_ft", ds.q, ds.qd, ds.qdd) + np.random.default_rng(
        0
    ).normal(0, 0.2, (len(ds), 6))
    r = ds.ft - predict_free(model, "base_ft", ds.q, ds.qd, ds.qdd)
    blocks = time_blocks(ds.file_id, 100)
    rb = RegressorBlocks.build(model, ds, r, blocks)
    fit = fit_inertial(rb, range(len(blocks)), [], rcond=1e-7)
    R, _, _, _ = rb.combine(range(len(blocks)))
    scale = np.sqrt((R**2).sum(0))
    scale[scale == 0] = 1
    _, s, Vt = np.linalg.svd(R / scale)
    k = int((s > 1e-7 * s[0]).sum())
    assert fit.identifiable == k and k < 30 < fit.columns  # few directions seen
    x = np.r_[fit.offset, fit.delta] * scale
    assert np.abs(Vt[k:] @ x).max() < 1e-9 * np.abs(x).max()
