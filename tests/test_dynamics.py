"""Inverse dynamics and the forward pass against pinocchio on real robots, plus identities."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from robots import ROBOTS, TOL, PinRobot, load_model, random_state

import torchcontact as tc
from torchcontact.spatial import twist_in_frame

ARMS = ["panda", "ur5", "xarm7", "icub"]


@pytest.mark.parametrize("name", ARMS)
def test_inverse_dynamics_matches_pinocchio_float64(name):
    model = load_model(name)
    ref = PinRobot(ROBOTS[name](), model)
    q, qd, qdd = random_state(model, 32, seed=1)
    tau = model.inverse_dynamics(q, qd, qdd).numpy()
    expected = np.stack([ref.rnea(*(x[k].numpy() for x in (q, qd, qdd))) for k in range(32)])
    assert not np.allclose(tau[0], tau[1])  # frames differ: the batch is not one frame repeated
    np.testing.assert_allclose(tau, expected, **TOL[torch.float64])


@pytest.mark.parametrize("name", ARMS)
def test_inverse_dynamics_float32_relative(name):
    model32 = load_model(name, torch.float32)
    model64 = load_model(name)
    q, qd, qdd = random_state(model64, 64, seed=2)
    ref = model64.inverse_dynamics(q, qd, qdd)
    out = model32.inverse_dynamics(q.float(), qd.float(), qdd.float())
    assert out.dtype == torch.float32
    scale = ref.abs().max()
    assert (out.double() - ref).abs().max() <= TOL[torch.float32]["rel"] * scale


def test_forward_pass_matches_pinocchio_body_twists():
    model = load_model("icub")
    ref = PinRobot(ROBOTS["icub"](), model)
    pin = ref.pin
    q, qd, qdd = (x[0] for x in random_state(model, 1, seed=3))
    fp = model.forward_pass(q, qd, qdd)
    pin.rnea(ref.m, ref.d, ref.q(q.numpy()), ref.v(qd.numpy()), ref.v(qdd.numpy()))
    pin.forwardKinematics(ref.m, ref.d, ref.q(q.numpy()))  # rnea leaves oMi untouched
    pin.updateFramePlacements(ref.m, ref.d)
    for jid, b in ref.joints:
        v_body = twist_in_frame(fp.R[b], fp.p[b], fp.v[b]).numpy()
        a_body = twist_in_frame(fp.R[b], fp.p[b], fp.a[b]).numpy()
        np.testing.assert_allclose(v_body, ref.d.v[jid].vector, atol=1e-9)
        np.testing.assert_allclose(a_body, ref.d.a_gf[jid].vector, atol=1e-9)
        np.testing.assert_allclose(fp.R[b].numpy(), ref.d.oMi[jid].rotation, atol=1e-12)
        np.testing.assert_allclose(fp.p[b].numpy(), ref.d.oMi[jid].translation, atol=1e-12)
    # a fixed frame (an iCub skin/DH frame merged into its body) is addressable by name
    R, p = model.frame_pose(fp, "l_hand_dh_frame")
    fid = ref.m.getFrameId("l_hand_dh_frame")
    np.testing.assert_allclose(R.numpy(), ref.d.oMf[fid].rotation, atol=1e-12)
    np.testing.assert_allclose(p.numpy(), ref.d.oMf[fid].translation, atol=1e-12)


def test_external_wrenches_match_pinocchio_fext():
    model = load_model("panda")
    ref = PinRobot(ROBOTS["panda"](), model)
    pin = ref.pin
    q, qd, qdd = random_state(model, 4, seed=4)
    g = torch.Generator().manual_seed(5)
    f_ext = torch.randn(4, model.nb, 6, generator=g, dtype=torch.float64) * 10
    f_ext[:, 0] = 0  # the root takes no external wrench in pinocchio's fixed-base rnea
    tau = model.inverse_dynamics(q, qd, qdd, f_ext=f_ext).numpy()
    for k in range(4):
        fext = [pin.Force.Zero() for _ in range(ref.m.njoints)]
        for jid, b in ref.joints:
            fext[jid] = pin.Force(f_ext[k, b].numpy())
        expected = ref.rnea(q[k].numpy(), qd[k].numpy(), qdd[k].numpy(), fext)
        np.testing.assert_allclose(tau[k], expected, atol=1e-9)


def test_linearity_in_external_wrenches_and_identities():
    model = load_model("ur5")
    q, qd, qdd = random_state(model, 8, seed=6)
    g = torch.Generator().manual_seed(7)
    f1, f2 = (torch.randn(8, model.nb, 6, generator=g, dtype=torch.float64) for _ in range(2))
    tau0 = model.inverse_dynamics(q, qd, qdd)
    t1 = model.inverse_dynamics(q, qd, qdd, f_ext=f1) - tau0
    t2 = model.inverse_dynamics(q, qd, qdd, f_ext=f2) - tau0
    t12 = model.inverse_dynamics(q, qd, qdd, f_ext=2 * f1 + 3 * f2) - tau0
    torch.testing.assert_close(t12, 2 * t1 + 3 * t2, atol=1e-10, rtol=0)
    # tau = M qdd + nle, with nle = rnea(q, qd, 0) and M's columns from unit accelerations
    nle = model.inverse_dynamics(q, qd, torch.zeros_like(qdd))
    g0 = model.inverse_dynamics(q, torch.zeros_like(qd), torch.zeros_like(qdd))
    eye = torch.eye(model.nv, dtype=torch.float64)
    M = torch.stack(
        [
            model.inverse_dynamics(q, torch.zeros_like(qd), eye[i].expand_as(q)) - g0
            for i in range(model.nv)
        ],
        dim=-1,
    )
    torch.testing.assert_close(tau0, (M @ qdd.unsqueeze(-1)).squeeze(-1) + nle, atol=1e-10, rtol=0)
    torch.testing.assert_close(M, M.transpose(-1, -2), atol=1e-12, rtol=0)  # symmetric


def test_moving_base_matches_pinocchio_free_flyer():
    import pinocchio as pin

    model = load_model("icub")
    ref = PinRobot(ROBOTS["icub"](), model, free_flyer=True)
    rng = np.random.default_rng(8)
    for _ in range(5):
        q, qd, qdd = (rng.uniform(-1, 1, model.nv) for _ in range(3))
        quat = rng.normal(size=4)
        quat /= np.linalg.norm(quat)
        base_q = np.concatenate([rng.uniform(-1, 1, 3), quat])  # x y z qx qy qz qw
        v_base = rng.uniform(-1, 1, 6)  # [linear; angular] in the base frame
        a_base = rng.uniform(-2, 2, 6)  # spatial acceleration in the base frame
        tau_pin = pin.rnea(ref.m, ref.d, ref.q(q, base_q), ref.v(qd, v_base), ref.v(qdd, a_base))
        R_wb = pin.Quaternion(quat[3], *quat[:3]).matrix()
        g_base = R_wb.T @ ref.m.gravity.linear
        # what an IMU at the base origin measures: classical acceleration minus gravity
        proper = a_base[:3] + np.cross(v_base[3:], v_base[:3]) - g_base
        base = tc.BaseMotion(*(torch.tensor(x) for x in (v_base[3:], a_base[3:], proper)))
        tau = tc.inverse_dynamics(model, *(torch.tensor(x) for x in (q, qd, qdd)), base=base)
        np.testing.assert_allclose(tau.numpy(), ref.fold_tau(tau_pin), atol=1e-9)


CONTINUOUS_URDF = """<robot name="two">
  <link name="base"/>
  <link name="a"><inertial><origin xyz="0.1 0.02 0.3" rpy="0.3 -0.2 0.1"/><mass value="1.3"/>
    <inertia ixx="0.02" ixy="0.001" ixz="-0.002" iyy="0.03" iyz="0.0005" izz="0.025"/></inertial></link>
  <link name="b"><inertial><origin xyz="0.0 0.1 0.05" rpy="0 0 0"/><mass value="0.7"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.012" iyz="0" izz="0.008"/></inertial></link>
  <link name="c"><inertial><origin xyz="0.05 0 0" rpy="0 0 0"/><mass value="0.4"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.002" iyz="0" izz="0.002"/></inertial></link>
  <joint name="j1" type="continuous"><parent link="base"/><child link="a"/>
    <origin xyz="0 0 0.1" rpy="0.1 0.2 0.3"/><axis xyz="0.3 0.5 0.8"/></joint>
  <joint name="j2" type="prismatic"><parent link="a"/><child link="b"/>
    <origin xyz="0.2 0 0.3" rpy="0 0.4 0"/><axis xyz="1 1 0"/>
    <limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="a"/><child link="c"/>
    <origin xyz="0 0.2 0.3" rpy="0.5 0 0"/><axis xyz="0 0 -1"/>
    <limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
</robot>"""


def test_continuous_prismatic_branching_tree_matches_pinocchio(tmp_path):
    path = tmp_path / "two.urdf"
    path.write_text(CONTINUOUS_URDF)
    model = tc.RobotModel.from_urdf(path)
    assert model.joint_names == ("j1", "j2", "j3")
    assert model.joint_types == ("continuous", "prismatic", "revolute")
    ref = PinRobot(path, model)
    q, qd, qdd = random_state(model, 6, seed=9)
    tau = model.inverse_dynamics(q, qd, qdd).numpy()
    for k in range(6):
        np.testing.assert_allclose(
            tau[k], ref.rnea(q[k].numpy(), qd[k].numpy(), qdd[k].numpy()), atol=1e-12
        )


def test_mimic_finger_follows_leader():
    model = load_model("panda")
    assert "panda_finger_joint2" not in model.joint_names  # a mimic joint is no coordinate
    b1, b2 = (
        model.body_joint.index("panda_finger_joint1"),
        model.body_joint.index("panda_finger_joint2"),
    )
    lead = model.joint_names.index("panda_finger_joint1")
    assert model.q_to_body[lead, b1] == 1 and model.q_to_body[lead, b2] == 1
    q, qd, qdd = (torch.zeros(model.nv, dtype=torch.float64) for _ in range(3))
    q[lead] = 0.03
    fp = model.forward_pass(q, qd, qdd)
    # both fingers open symmetrically: their distance grows by 2 * 0.03 m from q = 0
    d = (fp.p[b1] - fp.p[b2]).norm()
    fp0 = model.forward_pass(torch.zeros_like(q), qd, qdd)
    assert abs(d - (fp0.p[b1] - fp0.p[b2]).norm() - 0.06) < 1e-12


@pytest.mark.parametrize("shape", [(), (1,), (7,), (2, 3)])
def test_batch_shapes_and_batched_equals_loop(shape):
    model = load_model("panda")
    n = int(np.prod(shape)) if shape else 1
    q, qd, qdd = (x.reshape(*shape, model.nv) for x in random_state(model, n, seed=10))
    tau = model.inverse_dynamics(q, qd, qdd)
    assert tau.shape == (*shape, model.nv)
    flat = [x.reshape(n, model.nv) for x in (q, qd, qdd)]
    loop = torch.stack([model.inverse_dynamics(*(x[k] for x in flat)) for k in range(n)])
    torch.testing.assert_close(tau.reshape(n, model.nv), loop, atol=1e-12, rtol=0)
    fp = model.forward_pass(q, qd, qdd)
    assert fp.R.shape == (*shape, model.nb, 3, 3) and fp.a.shape == (*shape, model.nb, 6)


def test_chunking_agrees():
    model = load_model("ur5")
    q, qd, qdd = random_state(model, 1000, seed=11)
    full = model.inverse_dynamics(q, qd, qdd, chunk_size=None)
    chunked = model.inverse_dynamics(q, qd, qdd, chunk_size=128)
    torch.testing.assert_close(chunked, full, atol=1e-12, rtol=0)


def test_compiled_path_agrees_with_eager():
    model = tc.RobotModel.from_urdf(io.StringIO(CONTINUOUS_URDF))
    q, qd, qdd = random_state(model, 300, seed=14)  # not a multiple of the chunk: padded
    run = tc.compiled_inverse_dynamics(model, chunk_size=128)
    torch.testing.assert_close(
        run(q, qd, qdd), model.inverse_dynamics(q, qd, qdd), atol=1e-12, rtol=0
    )


def test_gravity_on_the_model_and_autograd_gradcheck():
    model = tc.RobotModel.from_urdf(io.StringIO(CONTINUOUS_URDF))
    q, qd, qdd = (x.requires_grad_() for x in random_state(model, 3, seed=12))
    torch.autograd.gradcheck(
        lambda q, qd, qdd: tc.inverse_dynamics(model, q, qd, qdd), (q, qd, qdd)
    )
    # gravity lives on the model; a per-frame gravity is a base acceleration of -g (at rest)
    grav = torch.tensor([[0.0, 0, -9.81], [0, -9.81, 0], [1.0, 2, 3]], dtype=torch.float64)
    q, qd, qdd = (x.detach() for x in (q, qd, qdd))
    zero = torch.zeros(3, 3, dtype=torch.float64)
    per_frame = tc.inverse_dynamics(model, q, qd, qdd, base=tc.BaseMotion(zero, zero, -grav))
    for k in range(3):
        m = model.with_gravity(grav[k])
        torch.testing.assert_close(
            m.inverse_dynamics(q[k], qd[k], qdd[k]), per_frame[k], atol=1e-12, rtol=0
        )
    assert model.gravity.tolist() == [0.0, 0.0, -9.81]  # with_gravity returned copies
    with pytest.raises(ValueError, match="gravity must be 3 finite numbers"):
        model.with_gravity((0.0, float("nan"), 1.0))


def test_bad_inputs_name_the_argument():
    model = load_model("ur5")
    q = torch.zeros(4, model.nv, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"qd must have shape \(\*B, 6\)"):
        model.inverse_dynamics(q, torch.zeros(4, 5, dtype=torch.float64), q)
    with pytest.raises(ValueError, match="share their batch shape"):
        model.inverse_dynamics(q, q[:2], q)
    bad = q.clone()
    bad[2, 3] = float("nan")
    with pytest.raises(ValueError, match=r"qdd contains NaN.*\(2, 3\)"):
        model.inverse_dynamics(q, q, bad)
    with pytest.raises(ValueError, match="q has dtype torch.float32"):
        model.inverse_dynamics(q.float(), q, q)
    with pytest.raises(ValueError, match="q is on meta"):
        model.inverse_dynamics(q.to("meta"), q, q)
    with pytest.raises(ValueError, match=r"f_ext must have shape \(\*B, 7, 6\)"):
        model.inverse_dynamics(q, q, q, f_ext=torch.zeros(4, 6, 6, dtype=torch.float64))
    with pytest.raises(ValueError, match="q must be a torch.Tensor"):
        model.inverse_dynamics(np.zeros((4, 6)), q, q)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    model = load_model("icub")
    q, qd, qdd = random_state(model, 256, seed=13)
    cpu = model.inverse_dynamics(q, qd, qdd)
    gpu = model.to("cuda").inverse_dynamics(q.cuda(), qd.cuda(), qdd.cuda())
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-9, rtol=0)


def test_finite_check_and_counts_on_large_and_strided_inputs():
    """The finite check sums CPU arrays with numpy (no OpenMP region): NaN and inf are still
    found in large, transposed and float32 inputs; counts round to the nearest integer."""
    from torchcontact._internal import counts

    model = load_model("ur5")
    n = 8192  # 49,152 values: above torch's parallel grain
    q = torch.zeros(n, model.nv, dtype=torch.float64)
    for value, where in ((float("nan"), (4000, 5)), (float("inf"), (8191, 0))):
        bad = q.clone()
        bad[where] = value
        with pytest.raises(ValueError, match=rf"q contains NaN or inf.*\({where[0]}, {where[1]}\)"):
            model.inverse_dynamics(bad, q, q)
    strided = torch.zeros(model.nv, n, dtype=torch.float64)
    strided[2, 7] = float("nan")
    with pytest.raises(ValueError, match=r"qd contains NaN or inf.*\(7, 2\)"):
        model.inverse_dynamics(q, strided.t(), q)
    m32 = model.to(dtype=torch.float32)
    bad32 = torch.zeros(n, model.nv)
    bad32[1, 1] = float("nan")
    with pytest.raises(ValueError, match=r"qdd contains NaN or inf.*\(1, 1\)"):
        m32.inverse_dynamics(torch.zeros_like(bad32), torch.zeros_like(bad32), bad32)
    x = torch.tensor([0.0, 0.49, 0.5, 2.9999999, 3.0000001, 6.0, 12.4], dtype=torch.float64)
    assert counts(x).tolist() == [0, 0, 1, 3, 3, 6, 12]
    assert counts(x).dtype == torch.int64
