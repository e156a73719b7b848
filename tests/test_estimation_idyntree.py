"""Contact estimation against iDynTree and independent least-squares computations.

Reference: iDynTree's ``ExtWrenchesAndJointTorquesEstimator`` (the Python bindings of the version
installed with the test extra, checked with 15.1) on iCubGenova04 from ``icub-models``: whole robot,
fixed ``root_link``, gravity ``(0, 0, -9.81)`` in the root frame, its six F/T sensors read from the
URDF. pinocchio's ``rnea`` with ``fext`` is the second reference for joint torques; numpy's
``lstsq``/``pinv`` on a matrix A built column by column from ``predict_ft`` is the reference for the
least-squares (minimum-norm) solutions and the covariance.

iDynTree conventions used here (checked against its headers and by experiment):

* a ``ContactWrench`` is the wrench the environment exerts on the link, link-frame orientation,
  moment about its ``contactPoint`` -- torchcontact's convention;
* the ``knownWrench`` of a ``NO_UNKNOWNS`` contact is, in 15.1, also taken about the
  ``contactPoint`` (the header says "w.r.t. the origin of the link frame"; with that reading the
  predicted F/T measurements differ by up to 2 N, about the contact point they agree to 1e-14);
* the root submodel (the bodies on the root side of every F/T sensor) needs its own unknown: a full
  wrench at the ``root_link`` origin (the fixed-base reaction). torchcontact has no unknown there.

Tolerances: float64 to 1e-9 absolute (``robots.TOL``) unless a line says why.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from robots import ROBOTS, TOL, PinRobot, load_model, random_state

import torchcontact as tc
from torchcontact.spatial import transform_wrench

idt = pytest.importorskip("idyntree.swig")

ATOL = TOL[torch.float64]["atol"]
DT = torch.float64


# ---------------------------------------------------------------------------------- references
class IDynTreeRef:
    """iDynTree's estimator on the same URDF and joint order as a torchcontact model."""

    KIND = {
        "wrench": "FULL_WRENCH",
        "force": "PURE_FORCE",
        "force_dir": "PURE_FORCE_WITH_KNOWN_DIRECTION",
        "known": "NO_UNKNOWNS",
    }

    def __init__(self, path, model: tc.RobotModel):
        self.est = idt.ExtWrenchesAndJointTorquesEstimator()
        assert self.est.loadModelAndSensorsFromFileWithSpecifiedDOFs(
            str(path), list(model.joint_names)
        )
        self.m = self.est.model()
        dofs = [self.m.getJointName(j) for j in range(self.m.getNrOfDOFs())]
        assert dofs == list(model.joint_names)  # same coordinate order: no permutation needed
        self.sens = self.est.sensors()
        T = idt.SIX_AXIS_FORCE_TORQUE
        self.ft_names = [
            self.sens.getSensor(T, i).getName() for i in range(self.sens.getNrOfSensors(T))
        ]
        self.root = self.m.getFrameIndex("root_link")

    def kinematics(self, q, qd, qdd, gravity=(0.0, 0.0, -9.81)):
        assert self.est.updateKinematicsFromFixedBase(
            idt.JointPosDoubleArray.FromPython(np.asarray(q, float)),
            idt.JointDOFsDoubleArray.FromPython(np.asarray(qd, float)),
            idt.JointDOFsDoubleArray.FromPython(np.asarray(qdd, float)),
            self.root,
            idt.Vector3.FromPython(list(gravity)),
        )

    def kinematics_floating(self, q, qd, qdd, omega, domega, proper_acc):
        """The floating-base update: an IMU on root_link (its frame), as torchcontact's base."""
        assert self.est.updateKinematicsFromFloatingBase(
            idt.JointPosDoubleArray.FromPython(np.asarray(q, float)),
            idt.JointDOFsDoubleArray.FromPython(np.asarray(qd, float)),
            idt.JointDOFsDoubleArray.FromPython(np.asarray(qdd, float)),
            self.root,
            idt.Vector3.FromPython(np.asarray(proper_acc, float)),
            idt.Vector3.FromPython(np.asarray(omega, float)),
            idt.Vector3.FromPython(np.asarray(domega, float)),
        )

    def unknowns(self, contacts):
        """``contacts``: list of (link, kind, point (3,), direction (3,) or None, wrench or None)."""
        u = idt.LinkUnknownWrenchContacts(self.m)
        u.clear()
        assert u.addNewUnknownFullWrenchInFrameOrigin(self.m, self.root)
        for link, kind, p, d, w in contacts:
            li = self.m.getLinkIndex(link)
            assert li >= 0, link
            c = idt.UnknownWrenchContact()
            c.unknownType = getattr(idt, self.KIND[kind])
            c.contactPoint = idt.Position.FromPython(np.asarray(p, float))
            if d is not None:
                c.forceDirection = idt.Direction(*(float(x) for x in d))
            if w is not None:  # about the contact point (see the module docstring)
                c.knownWrench = idt.Wrench.FromPython(np.asarray(w, float))
            u.addNewContactForLink(li, c)
        return u

    def predict(self, contacts) -> dict[str, np.ndarray]:
        meas = idt.SensorsMeasurements(self.sens)
        cw, tau = idt.LinkContactWrenches(self.m), idt.JointDOFsDoubleArray(self.m)
        assert self.est.computeExpectedFTSensorsMeasurements(self.unknowns(contacts), meas, cw, tau)
        out = {}
        for i, name in enumerate(self.ft_names):
            w = idt.Wrench()
            assert meas.getMeasurement(idt.SIX_AXIS_FORCE_TORQUE, i, w)
            out[name] = w.toNumPy().copy()
        return out

    def estimate(self, readings, contacts):
        """Contact wrenches ``(K, 6)`` in ``contacts`` order and joint torques ``(nv,)``."""
        meas = idt.SensorsMeasurements(self.sens)
        for i, name in enumerate(self.ft_names):
            w = idt.Wrench.FromPython(np.asarray(readings[name], float))
            assert meas.setMeasurement(idt.SIX_AXIS_FORCE_TORQUE, i, w)
        cw, tau = idt.LinkContactWrenches(self.m), idt.JointDOFsDoubleArray(self.m)
        assert self.est.estimateExtWrenchesAndJointTorques(self.unknowns(contacts), meas, cw, tau)
        seen: dict[int, int] = {}
        out = []
        for link, *_ in contacts:
            li = self.m.getLinkIndex(link)
            k = seen.get(li, 0)
            seen[li] = k + 1
            out.append(cw.contactWrench(li, k).contactWrench.toNumPy().copy())
        return np.array(out), tau.toNumPy().copy()


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small per-frame tensors: intra-op threads only add overhead, and with iDynTree/pinocchio
    loaded on the 2-core CI machine they made index_add ~1000x slower (test time 40 s -> 7 s)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def icub():
    model = load_model("icub")
    return model, tc.ContactEstimator(model), IDynTreeRef(ROBOTS["icub"](), model)


def true_wrenches(kinds, n, seed, directions=None):
    """Random contact wrenches ``(n, K, 6)`` that fit their kinds (about the contact point)."""
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(n, len(kinds), 6, generator=g, dtype=DT) * 10
    for k, kind in enumerate(kinds):
        if kind in ("force", "force_dir"):
            w[:, k, 3:] = 0
        if kind == "force_dir":
            d = directions[:, k] / directions[:, k].norm(dim=-1, keepdim=True)
            w[:, k, :3] = d * w[:, k, :1]
    return w


def random_contacts(links, kinds, n, seed, scale=0.05):
    g = torch.Generator().manual_seed(seed)
    pos = torch.randn(n, len(links), 3, generator=g, dtype=DT) * scale
    dirs = torch.randn(n, len(links), 3, generator=g, dtype=DT)
    wr = true_wrenches(kinds, n, seed + 1, dirs)
    return pos, dirs, wr


def fext_of(model, links, pos, wr):
    """Contact wrenches (link frame, about the point) -> per-body f_ext about the body origin."""
    f = torch.zeros(model.nb, 6, dtype=DT)
    for k, link in enumerate(links):
        fr = model.frame(link)
        R = torch.as_tensor(fr.R_body_frame, dtype=DT)
        p = torch.as_tensor(fr.p_body_frame, dtype=DT) + R @ pos[k]
        f[fr.body] += transform_wrench(R, p, wr[k])
    return f


def pin_tau(pinrobot, q, qd, qdd, links, pos, wr):
    """pinocchio's rnea with the contacts as ``fext`` (pinocchio merges the F/T sensor joints, so
    each contact goes to its link's pinocchio frame, then to the parent joint's frame)."""
    pin = pinrobot.pin
    fext = [pin.Force.Zero() for _ in range(pinrobot.m.njoints)]
    for k, link in enumerate(links):
        fr = pinrobot.m.frames[pinrobot.m.getFrameId(link)]
        w_link = transform_wrench(torch.eye(3, dtype=DT), pos[k], wr[k])  # about the link origin
        fext[fr.parentJoint] += fr.placement.act(pin.Force(w_link.numpy()))
    return pinrobot.rnea(q.numpy(), qd.numpy(), qdd.numpy(), fext)


def build_A(est, q, qd, qdd, links, kinds, pos, dirs):
    """Reading-space matrix of every frame, column by column from ``predict_ft`` (A is linear).

    Returns ``A (n, 6 S, U)``, the zero-contact readings ``(n, 6 S)``, the basis ``B (n, K, 6, U)``
    with ``w_k = B_k x`` and the slot of each column ``(U,)``.
    """
    n, K = pos.shape[:2]
    cols = []  # (slot, basis wrench (n, 6))
    for k, kind in enumerate(kinds):
        if kind == "wrench":
            basis = [torch.eye(6, dtype=DT)[i].expand(n, 6) for i in range(6)]
        elif kind == "force":
            basis = [torch.eye(6, dtype=DT)[i].expand(n, 6) for i in range(3)]
        elif kind == "force_dir":
            d = dirs[:, k] / dirs[:, k].norm(dim=-1, keepdim=True)
            basis = [torch.cat((d, torch.zeros_like(d)), -1)]
        else:
            basis = []
        cols += [(k, b) for b in basis]

    def readings(w):
        c = tc.Contacts(links, ["known"] * K, pos, wrenches=w)
        r = est.predict_ft(q, qd, qdd, c)
        return torch.cat([r[s] for s in est.sensor_names], -1)

    r0 = readings(torch.zeros(n, K, 6, dtype=DT))
    A = torch.zeros(n, 6 * len(est.sensor_names), len(cols), dtype=DT)
    B = torch.zeros(n, K, 6, len(cols), dtype=DT)
    for j, (k, b) in enumerate(cols):
        w = torch.zeros(n, K, 6, dtype=DT)
        w[:, k] = b
        A[:, :, j] = readings(w) - r0
        B[:, k, :, j] = b
    return A.numpy(), r0.numpy(), B.numpy(), np.array([k for k, _ in cols])


def stack_ft(est, ft):
    return torch.cat([ft[s] for s in est.sensor_names], -1).numpy()


# ---------------------------------------------------------------------------------- a. forward
@pytest.mark.parametrize("backend", ["eager", "cpu"])
def test_predicted_ft_matches_idyntree(icub, backend):
    model, est, ref = icub
    links = ["l_forearm", "l_hand", "r_lower_leg", "l_foot", "r_upper_arm", "l_upper_leg"]
    n = 4
    q, qd, qdd = random_state(model, n, seed=10)
    pos, _, wr = random_contacts(links, ["wrench"] * len(links), n, seed=11)
    c = tc.Contacts(links, ["known"] * len(links), pos, wrenches=wr)
    ours = est.predict_ft(q, qd, qdd, c, backend=backend)
    assert set(ours) == set(ref.ft_names)
    assert not np.allclose(ours["l_arm_ft"][0], ours["l_arm_ft"][1])
    for i in range(n):
        ref.kinematics(q[i], qd[i], qdd[i])
        theirs = ref.predict(
            [(lk, "known", pos[i, k].numpy(), None, wr[i, k].numpy()) for k, lk in enumerate(links)]
        )
        for s in ref.ft_names:
            np.testing.assert_allclose(ours[s][i].numpy(), theirs[s], atol=ATOL, rtol=0)
    # the contacts matter: without them the arm sensor reads something else
    free = est.predict_ft(q, qd, qdd, tc.Contacts((), (), torch.zeros(n, 0, 3, dtype=DT)))
    assert (free["l_arm_ft"] - ours["l_arm_ft"]).abs().max() > 1.0


# ---------------------------------------------------------------------------------- b. estimation
# One region each: l_arm a full wrench, r_leg a pure force, l_foot six known-direction forces,
# r_arm a pure force, l_leg two known-direction forces; r_foot no contact.
B_LINKS = ["l_hand", "r_lower_leg", *["l_foot"] * 6, "r_forearm", "l_upper_leg", "l_upper_leg"]
B_KINDS = ["wrench", "force", *["force_dir"] * 6, "force", "force_dir", "force_dir"]


# eager only: the generated kernel equals eager on every output of the whole robot with every
# contact kind (tests/test_kernels.py), and this kernel's build costs 20-27 s of the suite
@pytest.mark.parametrize("backend", ["eager"])
def test_estimate_matches_idyntree_pinocchio_and_truth(icub, backend):
    model, est, ref = icub
    pinrobot = PinRobot(ROBOTS["icub"](), model)
    n = 3
    q, qd, qdd = random_state(model, n, seed=20)
    pos, dirs, wr = random_contacts(B_LINKS, B_KINDS, n, seed=21)
    K = len(B_LINKS)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(B_LINKS, ["known"] * K, pos, wrenches=wr),
                        backend=backend)  # fmt: skip
    out = est.estimate(q, qd, qdd, ft, tc.Contacts(B_LINKS, B_KINDS, pos, directions=dirs),
                       backend=backend)  # fmt: skip
    w_est = torch.cat((out.force, out.moment), -1)
    assert (out.status == 0).all()
    for s in est.sensor_names:
        assert bool(out.identifiable[s].all()), s
    assert out.unknowns["l_foot_ft"].tolist() == [6] * n
    assert out.unknowns["r_foot_ft"].tolist() == [0] * n
    # ours vs the truth; the truth's scale is 10 N, the worst conditioning (six forces on a foot
    # with 5 cm lever arms) amplifies rounding to ~1e-12
    np.testing.assert_allclose(w_est.numpy(), wr.numpy(), atol=ATOL, rtol=0)
    tau_ref = model.inverse_dynamics(
        q, qd, qdd, f_ext=torch.stack([fext_of(model, B_LINKS, pos[i], wr[i]) for i in range(n)])
    )
    for i in range(n):
        ref.kinematics(q[i], qd[i], qdd[i])
        readings = {s: ft[s][i].numpy() for s in est.sensor_names}
        spec = [
            (lk, kd, pos[i, k].numpy(), dirs[i, k].numpy() if kd == "force_dir" else None, None)
            for k, (lk, kd) in enumerate(zip(B_LINKS, B_KINDS, strict=True))
        ]
        w_idt, tau_idt = ref.estimate(readings, spec)
        np.testing.assert_allclose(w_idt, wr[i].numpy(), atol=ATOL, rtol=0)
        np.testing.assert_allclose(w_est[i].numpy(), w_idt, atol=ATOL, rtol=0)
        tau_pin = pin_tau(pinrobot, q[i], qd[i], qdd[i], B_LINKS, pos[i], wr[i])
        np.testing.assert_allclose(out.joint_torques[i].numpy(), tau_idt, atol=ATOL, rtol=0)
        np.testing.assert_allclose(out.joint_torques[i].numpy(), tau_pin, atol=ATOL, rtol=0)
        np.testing.assert_allclose(tau_ref[i].numpy(), tau_pin, atol=ATOL, rtol=0)
    # the contacts change the torques: the comparison is not gravity alone
    tau0 = model.inverse_dynamics(q, qd, qdd)
    assert (tau0 - out.joint_torques).abs().max() > 1.0


# eager only: the generated kernel equals eager with a moving base on every output
# (tests/test_kernels.py), and a whole-robot moving-base kernel build costs 20 s of the suite
@pytest.mark.parametrize("backend", ["eager"])
def test_moving_base_matches_idyntree_floating_base(icub, backend):
    """An IMU on the base: iDynTree's estimator after updateKinematicsFromFloatingBase."""
    model, est, ref = icub
    n = 3
    q, qd, qdd = random_state(model, n, seed=25)
    g = torch.Generator().manual_seed(26)
    base = tc.BaseMotion(
        torch.randn(n, 3, generator=g, dtype=DT),  # omega, rad/s
        torch.randn(n, 3, generator=g, dtype=DT) * 2,  # domega, rad/s^2
        torch.randn(n, 3, generator=g, dtype=DT) * 3 + torch.tensor([0, 0, 9.81], dtype=DT),
    )
    pos, dirs, wr = random_contacts(B_LINKS, B_KINDS, n, seed=27)
    K = len(B_LINKS)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(B_LINKS, ["known"] * K, pos, wrenches=wr),
                        base=base, backend=backend)  # fmt: skip
    out = est.estimate(q, qd, qdd, ft, tc.Contacts(B_LINKS, B_KINDS, pos, directions=dirs),
                       base=base, backend=backend)  # fmt: skip
    assert (out.status == 0).all()
    w_est = torch.cat((out.force, out.moment), -1)
    np.testing.assert_allclose(w_est.numpy(), wr.numpy(), atol=ATOL, rtol=0)
    for i in range(n):
        ref.kinematics_floating(q[i], qd[i], qdd[i], *(x[i].numpy() for x in base))
        theirs = ref.predict(
            [
                (lk, "known", pos[i, k].numpy(), None, wr[i, k].numpy())
                for k, lk in enumerate(B_LINKS)
            ]
        )
        for s in ref.ft_names:
            np.testing.assert_allclose(ft[s][i].numpy(), theirs[s], atol=ATOL, rtol=0)
        spec = [
            (lk, kd, pos[i, k].numpy(), dirs[i, k].numpy() if kd == "force_dir" else None, None)
            for k, (lk, kd) in enumerate(zip(B_LINKS, B_KINDS, strict=True))
        ]
        w_idt, tau_idt = ref.estimate({s: ft[s][i].numpy() for s in est.sensor_names}, spec)
        np.testing.assert_allclose(w_est[i].numpy(), w_idt, atol=ATOL, rtol=0)
        np.testing.assert_allclose(out.joint_torques[i].numpy(), tau_idt, atol=ATOL, rtol=0)
    # the base motion matters: the fixed-base estimate of the same readings differs
    fixed = est.estimate(q, qd, qdd, ft, tc.Contacts(B_LINKS, B_KINDS, pos, directions=dirs))
    assert (fixed.joint_torques - out.joint_torques).abs().max() > 1e-2


def region_blocks(est, links, col_slot):
    """Per used sensor: its 6 reading rows and the columns of the slots in its region."""
    model = est.model
    region = np.array([est.region[model.frame(lk).body] for lk in links])
    out = {}
    for i, s in enumerate(est.sensor_names):
        cols = np.flatnonzero(region[col_slot] == i)
        out[s] = (np.arange(6 * i, 6 * i + 6), cols)
    return out


def pinv_solution(A, b, blocks, rcond=1e-7):
    """Minimum-norm least squares, region by region (A is block diagonal by region).

    ``rcond`` 1e-7 sits between the estimator's default singular-value cut (3.7e-8 sigma_max) and
    the smallest kept singular value of these cases (above 1e-3 sigma_max); the zero ones are
    ~1e-16 sigma_max.
    """
    x = np.zeros(A.shape[1])
    rank, res = {}, {}
    for s, (rows, cols) in blocks.items():
        if len(cols) == 0:
            rank[s], res[s] = 0, np.linalg.norm(b[rows])
            continue
        Ab = A[np.ix_(rows, cols)]
        xs, _, rk, sv = np.linalg.lstsq(Ab, b[rows], rcond=rcond)
        np.testing.assert_allclose(xs, np.linalg.pinv(Ab, rcond=rcond) @ b[rows], atol=1e-9)
        x[cols] = xs
        rank[s], res[s] = rk, np.linalg.norm(Ab @ xs - b[rows])
    return x, rank, res


# ---------------------------------------------------------------------------------- c. rank-deficient
# Regions of the arm sensors only: their parent side is the root region, so in reading space A is
# block diagonal by sensor (a contact on a foot would also move the leg sensor's reading, which the
# estimator replaces by the measured nested foot reading).
C_LINKS = ["l_hand", "l_forearm", "r_forearm", "r_hand"]
C_KINDS = ["wrench", "force", "force", "force"]


def test_underdetermined_is_minimum_norm_least_squares(icub):
    model, est, ref = icub
    n = 3
    q, qd, qdd = random_state(model, n, seed=30)
    pos, dirs, wr = random_contacts(C_LINKS, C_KINDS, n, seed=31)
    K = len(C_LINKS)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(C_LINKS, ["known"] * K, pos, wrenches=wr))
    g = torch.Generator().manual_seed(32)
    for s in ("l_arm_ft", "r_arm_ft"):  # inconsistent readings: residual > 0
        ft[s] = ft[s] + torch.randn(n, 6, generator=g, dtype=DT)
    c = tc.Contacts(C_LINKS, C_KINDS, pos)
    out = est.estimate(q, qd, qdd, ft, c)
    A, r0, B, col_slot = build_A(est, q, qd, qdd, C_LINKS, C_KINDS, pos, dirs)
    blocks = region_blocks(est, C_LINKS, col_slot)
    b = stack_ft(est, ft) - r0
    w_est = torch.cat((out.force, out.moment), -1).numpy()
    for i in range(n):
        x, rank, res = pinv_solution(A[i], b[i], blocks)
        w_ref = np.einsum("kju,u->kj", B[i], x)
        np.testing.assert_allclose(w_est[i], w_ref, atol=ATOL, rtol=0)
        for s in est.sensor_names:
            assert int(out.rank[s][i]) == rank[s], s
            np.testing.assert_allclose(float(out.residual[s][i]), res[s], atol=ATOL, rtol=0)
        # iDynTree's per-submodel solve is a least-squares solution too (same residual), but not
        # the minimum-norm one (it zeroes unknowns, like a basic solution): ours is no longer
        ref.kinematics(q[i], qd[i], qdd[i])
        spec = [
            (lk, kd, pos[i, k].numpy(), None, None)
            for k, (lk, kd) in enumerate(zip(C_LINKS, C_KINDS, strict=True))
        ]
        w_idt, _ = ref.estimate({s: ft[s][i].numpy() for s in est.sensor_names}, spec)
        x_idt = np.einsum("kju,kj->u", B[i], w_idt)
        np.testing.assert_allclose(np.einsum("kju,u->kj", B[i], x_idt), w_idt, atol=ATOL)
        _, _, res_idt = pinv_solution(A[i], b[i] - A[i] @ x_idt, blocks)
        for s in ("l_arm_ft", "r_arm_ft"):
            rows, cols = blocks[s]
            np.testing.assert_allclose(res_idt[s], res[s], atol=ATOL, rtol=0)
            assert np.linalg.norm(x[cols]) <= np.linalg.norm(x_idt[cols]) + ATOL
    assert out.rank["l_arm_ft"].tolist() == [6] * n and out.unknowns["l_arm_ft"].tolist() == [9] * n
    assert out.rank["r_arm_ft"].tolist() == [5] * n and out.unknowns["r_arm_ft"].tolist() == [6] * n
    assert not out.identifiable["r_arm_ft"].any() and not out.identifiable["l_arm_ft"].any()
    assert (out.residual["r_arm_ft"] > 1e-3).all()  # the noisy reading is not in A's range
    assert (out.residual["l_arm_ft"] < 1e-9).all()  # rank 6 = rows: any reading is consistent
    # min-norm: the truth is another solution, and not the estimate
    assert np.abs(w_est[:, 1] - wr[:, 1].numpy()).max() > 1e-3


# ---------------------------------------------------------------------------------- d. round trip
RPY = np.array([0.3, -0.2, 0.5])


def _rot(rpy):
    r, p, y = rpy
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


ROUND_TRIP = {
    "panda-wrist": ("panda", "panda_hand_joint", ["panda_hand"], ["wrench"]),
    "ur5-wrist": ("ur5", "ee_fixed_joint", ["ee_link"], ["wrench"]),
    "ur5-base": (
        "ur5",
        "world_joint",
        ["forearm_link", "wrist_2_link", "upper_arm_link"],
        ["force", "force_dir", "force_dir"],
    ),
}


@pytest.mark.parametrize("direction", ["child_to_parent", "parent_to_child"])
@pytest.mark.parametrize("frame", ["child", "parent", "sensor"])
@pytest.mark.parametrize("case", list(ROUND_TRIP))
def test_round_trip_declared_sensor(case, frame, direction):
    name, joint, links, kinds = ROUND_TRIP[case]
    base = tc.RobotModel.from_urdf(ROBOTS[name](), keep_fixed=[joint])
    extra = dict(R_child_sensor=_rot(RPY), p_child_sensor=[0.01, -0.02, 0.03])
    model = base.with_ft_sensor(
        "ft",
        joint,
        frame=frame,
        measure_direction=direction,
        **(extra if frame == "sensor" else {}),
    )
    est = tc.ContactEstimator(model, ["ft"])
    n = 4
    q, qd, qdd = random_state(model, n, seed=40)
    pos, dirs, wr = random_contacts(links, kinds, n, seed=41)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(links, ["known"] * len(links), pos, wrenches=wr))
    out = est.estimate(q, qd, qdd, ft, tc.Contacts(links, kinds, pos, directions=dirs))
    assert out.identifiable["ft"].all()
    w = torch.cat((out.force, out.moment), -1)
    torch.testing.assert_close(w, wr, atol=ATOL, rtol=0)
    f_ext = torch.stack([fext_of(model, links, pos[i], wr[i]) for i in range(n)])
    torch.testing.assert_close(
        out.joint_torques, model.inverse_dynamics(q, qd, qdd, f_ext=f_ext), atol=ATOL, rtol=0
    )
    # the declared convention changes the reading: frame rotation and sign are applied
    ref_model = base.with_ft_sensor("ft", joint, frame="child", measure_direction="parent_to_child")
    r_child = tc.ContactEstimator(ref_model, ["ft"]).predict_ft(
        q, qd, qdd, tc.Contacts(links, ["known"] * len(links), pos, wrenches=wr)
    )["ft"]
    sign = 1.0 if direction == "parent_to_child" else -1.0
    if frame == "child":
        torch.testing.assert_close(ft["ft"], sign * r_child, atol=ATOL, rtol=0)
    elif frame == "sensor":
        R, p = torch.as_tensor(_rot(RPY)), torch.tensor([0.01, -0.02, 0.03], dtype=DT)
        expected = tc.spatial.transform_wrench_inverse(R, p, r_child)
        torch.testing.assert_close(ft["ft"], sign * expected, atol=ATOL, rtol=0)


# ---------------------------------------------------------------------------------- e. batches
E_LINKS = ["l_hand", "l_hand", "l_forearm", "l_forearm", "r_hand", "r_forearm", "l_foot"]
E_KINDS = ["wrench", "force", "force_dir", "known", "force", "force_dir", "force"]


def _mixed(model, est, n, seed):
    q, qd, qdd = random_state(model, n, seed=seed)
    pos, dirs, wr = random_contacts(E_LINKS, E_KINDS, n, seed=seed + 1)
    g = torch.Generator().manual_seed(seed + 2)
    active = torch.rand(n, len(E_LINKS), generator=g) > 0.4
    active[0] = False  # a frame without any contact
    ft = est.predict_ft(
        q, qd, qdd, tc.Contacts(E_LINKS, ["known"] * len(E_LINKS), pos, wrenches=wr, active=active)
    )
    return q, qd, qdd, pos, dirs, wr, active, ft


def test_mixed_batch_equals_frame_by_frame(icub):
    model, est, _ = icub
    n = 7
    q, qd, qdd, pos, dirs, wr, active, ft = _mixed(model, est, n, seed=50)
    assert len({tuple(a.tolist()) for a in active}) > 3  # the frames use different slot sets
    c = tc.Contacts(E_LINKS, E_KINDS, pos, directions=dirs, wrenches=wr, active=active)
    out = est.estimate(q, qd, qdd, ft, c)
    for i in range(n):
        idx = [k for k in range(len(E_LINKS)) if active[i, k]]
        ci = tc.Contacts(
            [E_LINKS[k] for k in idx],
            [E_KINDS[k] for k in idx],
            pos[i, idx],
            directions=dirs[i, idx],
            wrenches=wr[i, idx],
        )
        oi = est.estimate(q[i], qd[i], qdd[i], {s: ft[s][i] for s in ft}, ci)
        torch.testing.assert_close(out.force[i, idx], oi.force, atol=ATOL, rtol=0)
        torch.testing.assert_close(out.moment[i, idx], oi.moment, atol=ATOL, rtol=0)
        off = [k for k in range(len(E_LINKS)) if not active[i, k]]
        assert (out.force[i, off] == 0).all() and (out.moment[i, off] == 0).all()
        torch.testing.assert_close(out.joint_torques[i], oi.joint_torques, atol=ATOL, rtol=0)
        for s in est.sensor_names:
            assert out.rank[s][i] == oi.rank[s] and out.unknowns[s][i] == oi.unknowns[s]
            torch.testing.assert_close(out.residual[s][i], oi.residual[s], atol=ATOL, rtol=0)
    # identifiable slots are the truth
    k_foot = E_LINKS.index("l_foot")
    on = active[:, k_foot]
    torch.testing.assert_close(out.force[on, k_foot], wr[on, k_foot, :3], atol=ATOL, rtol=0)


@pytest.mark.parametrize("shape", [(), (1,), (7,), (2, 3)])
def test_batch_shapes(icub, shape):
    model, est, _ = icub
    n = 7
    q, qd, qdd, pos, dirs, wr, active, ft = _mixed(model, est, n, seed=60)
    flat = est.estimate(q, qd, qdd, ft, tc.Contacts(E_LINKS, E_KINDS, pos, dirs, wr, active))
    m = int(np.prod(shape))

    def rs(x, trailing):
        return x[:m].reshape(*shape, *trailing)

    K = len(E_LINKS)
    out = est.estimate(
        rs(q, (model.nv,)),
        rs(qd, (model.nv,)),
        rs(qdd, (model.nv,)),
        {s: rs(v, (6,)) for s, v in ft.items()},
        tc.Contacts(
            E_LINKS, E_KINDS, rs(pos, (K, 3)), rs(dirs, (K, 3)), rs(wr, (K, 6)), rs(active, (K,))
        ),
    )
    assert out.force.shape == (*shape, K, 3) and out.joint_torques.shape == (*shape, model.nv)
    assert out.status.shape == shape and out.rank["l_arm_ft"].shape == shape
    torch.testing.assert_close(out.force, rs(flat.force, (K, 3)), atol=ATOL, rtol=0)
    torch.testing.assert_close(out.moment, rs(flat.moment, (K, 3)), atol=ATOL, rtol=0)
    torch.testing.assert_close(
        out.joint_torques, rs(flat.joint_torques, (model.nv,)), atol=ATOL, rtol=0
    )


# ---------------------------------------------------------------------------------- f. bad input
def test_bad_input_raises(icub):
    model, est, _ = icub
    q, qd, qdd = random_state(model, 2, seed=70)
    ft = {s: torch.zeros(2, 6, dtype=DT) for s in est.sensor_names}
    pos = torch.zeros(2, 1, 3, dtype=DT)
    with pytest.raises(ValueError, match="'chest'.*outside every F/T sensor"):
        est.estimate(q, qd, qdd, ft, tc.Contacts(["chest"], ["force"], pos))
    with pytest.raises(ValueError, match="unknown link.*l_handd"):
        est.estimate(q, qd, qdd, ft, tc.Contacts(["l_handd"], ["force"], pos))
    with pytest.raises(ValueError, match="unknown F/T sensors.*'l_wrist_ft'"):
        tc.ContactEstimator(model, ["l_arm_ft", "l_wrist_ft"])
    missing = {s: v for s, v in ft.items() if s != "r_foot_ft"}
    with pytest.raises(ValueError, match="missing readings.*r_foot_ft"):
        est.estimate(q, qd, qdd, missing, tc.Contacts(["l_hand"], ["force"], pos))


def test_bad_frames_get_status_and_nan_others_exact(icub):
    model, est, _ = icub
    n = 6
    q, qd, qdd, pos, dirs, wr, active, ft = _mixed(model, est, n, seed=80)
    k_dir = E_KINDS.index("force_dir")
    active[:, k_dir] = True
    ft = {s: v.clone() for s, v in ft.items()}
    ft["r_arm_ft"][1, 4] = float("nan")  # frame 1: NaN reading
    dirs = dirs.clone()
    dirs[3, k_dir] = 0.0  # frame 3: zero-length direction of an active force_dir slot
    # frame 4: NaN in the direction of an active force_dir slot (bit 4)
    dirs[4, k_dir] = float("nan")
    # frame 5: NaN in the direction of an active "force" slot, a field its kind does not use:
    # ignored, the frame is estimated normally (a log's null direction of a pure force is fine)
    dirs[5, E_KINDS.index("force")] = float("nan")
    c = tc.Contacts(E_LINKS, E_KINDS, pos, dirs, wr, active)
    out = est.estimate(q, qd, qdd, ft, c)
    assert out.status.tolist() == [0, 1, 0, 8, 4, 0]
    assert tc.status_messages(int(out.status[3])) == "zero-length contact direction"
    bad = torch.tensor([False, True, False, True, True, False])
    for x in (out.force, out.moment, out.joint_torques, out.residual["l_arm_ft"]):
        assert x[bad].isnan().all() and x[~bad].isfinite().all()
    dirs[5, E_KINDS.index("force")] = 0.0  # the reference run sees no NaN there at all
    good = [0, 2, 5]
    ref = est.estimate(
        q[good],
        qd[good],
        qdd[good],
        {s: v[good] for s, v in ft.items()},
        tc.Contacts(E_LINKS, E_KINDS, pos[good], dirs[good], wr[good], active[good]),
    )
    torch.testing.assert_close(out.force[good], ref.force, atol=ATOL, rtol=0)
    torch.testing.assert_close(out.joint_torques[good], ref.joint_torques, atol=ATOL, rtol=0)


# ---------------------------------------------------------------------------------- g. torque rows
def test_joint_torque_rows_make_it_identifiable(icub):
    model, est, _ = icub
    n = 3
    links, kinds = ["l_forearm", "l_hand"], ["force", "force"]
    q, qd, qdd = random_state(model, n, seed=90)
    pos, _, wr = random_contacts(links, kinds, n, seed=91)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(links, ["known"] * 2, pos, wrenches=wr))
    c = tc.Contacts(links, kinds, pos)
    plain = est.estimate(q, qd, qdd, ft, c)
    assert plain.rank["l_arm_ft"].tolist() == [5] * n  # the force along the line is unobservable
    w_plain = torch.cat((plain.force, plain.moment), -1)
    assert (w_plain - wr).abs().max() > 1e-3
    f_ext = torch.stack([fext_of(model, links, pos[i], wr[i]) for i in range(n)])
    tau = model.inverse_dynamics(q, qd, qdd, f_ext=f_ext)
    mask = torch.tensor([j.startswith(("l_elbow", "l_wrist")) for j in model.joint_names])
    assert int(mask.sum()) == 4
    out = est.estimate(q, qd, qdd, ft, c, tau_measured=tau, tau_mask=mask)
    assert out.rank["l_arm_ft"].tolist() == [6] * n and out.identifiable["l_arm_ft"].all()
    torch.testing.assert_close(torch.cat((out.force, out.moment), -1), wr, atol=ATOL, rtol=0)
    torch.testing.assert_close(out.joint_torques, tau, atol=ATOL, rtol=0)
    assert (out.residual["l_arm_ft"] < 1e-9).all()


# ---------------------------------------------------------------------------------- h. covariance
def test_covariance_is_pinv_sigma_pinv_t(icub):
    model, est, _ = icub
    n = 3
    links, kinds = C_LINKS, C_KINDS  # l_arm rank 6 of 9 unknowns, r_arm rank 5 of 6
    q, qd, qdd = random_state(model, n, seed=100)
    pos, dirs, wr = random_contacts(links, kinds, n, seed=101)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(links, ["known"] * len(links), pos, wrenches=wr))
    g = torch.Generator().manual_seed(102)
    sig = {}
    for s in est.sensor_names:
        L = torch.randn(6, 6, generator=g, dtype=DT)
        sig[s] = L @ L.T + 0.1 * torch.eye(6, dtype=DT)
    out = est.estimate(
        q, qd, qdd, ft, tc.Contacts(links, kinds, pos), ft_covariance=sig, weighted=False
    )  # the noise propagated through the paper's pinv
    A, _, B, col_slot = build_A(est, q, qd, qdd, links, kinds, pos, dirs)
    blocks = region_blocks(est, links, col_slot)
    for i in range(n):
        cov_x = np.zeros((A.shape[2], A.shape[2]))
        for s, (rows, cols) in blocks.items():
            if len(cols):
                Pi = np.linalg.pinv(A[i][np.ix_(rows, cols)], rcond=1e-7)
                cov_x[np.ix_(cols, cols)] = Pi @ sig[s].numpy() @ Pi.T
        cov_w = np.einsum("kau,uv,kbv->kab", B[i], cov_x, B[i])
        # covariances are N^2-scale numbers up to ~1e3 here: 1e-9 relative to their largest
        scale = np.abs(cov_w).max()
        np.testing.assert_allclose(out.covariance[i].numpy(), cov_w, atol=1e-9 * scale, rtol=0)
    assert out.covariance.shape == (n, len(links), 6, 6)
    assert (out.covariance[:, 0].diagonal(dim1=-2, dim2=-1) > 0).all()


# ---------------------------------------------------------------------------------- i. weighted
def _weighted_reference(A, b, blocks, sigmas, rcond=1e-7):
    """numpy weighted least squares of minimum norm, region by region: ``x = pinv(L^-1 A) L^-1
    b`` with ``Sigma = L L^T``, and the estimate's covariance ``pinv(L^-1 A) pinv(L^-1 A)^T``."""
    x = np.zeros(A.shape[1])
    cov = np.zeros((A.shape[1], A.shape[1]))
    for s, (rows, cols) in blocks.items():
        if len(cols) == 0:
            continue
        L = np.linalg.cholesky(sigmas[s])
        Aw = np.linalg.solve(L, A[np.ix_(rows, cols)])
        x[cols] = np.linalg.lstsq(Aw, np.linalg.solve(L, b[rows]), rcond=rcond)[0]
        P = np.linalg.pinv(Aw, rcond=rcond)
        cov[np.ix_(cols, cols)] = P @ P.T
    return x, cov


@pytest.fixture(scope="module")
def arms(icub):
    """The two arm sensors only: a smaller kernel than the whole robot's six regions."""
    model = icub[0]
    return model, tc.ContactEstimator(model, ["l_arm_ft", "r_arm_ft"])


@pytest.mark.parametrize("backend", ["eager", "cpu"])
def test_weighted_is_numpy_weighted_least_squares(arms, backend):
    """``ft_covariance`` weighs the solve: weighted least squares, minimum norm among its
    solutions (l_arm rank 6 of 9 unknowns, r_arm rank 5 of 6), per-frame covariances."""
    model, est = arms
    n = 3
    q, qd, qdd = random_state(model, n, seed=110)
    pos, dirs, wr = random_contacts(C_LINKS, C_KINDS, n, seed=111)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(C_LINKS, ["known"] * 4, pos, wrenches=wr))
    g = torch.Generator().manual_seed(112)
    sig = {}
    floor = torch.diag(torch.tensor([0.01] * 3 + [2.5e-5] * 3, dtype=DT))  # FT 300-like
    for s in est.sensor_names:
        M = torch.randn(n, 6, 6, generator=g, dtype=DT) * 0.05
        sig[s] = M @ M.transpose(-1, -2) + floor  # a different correlated noise per frame
        ft[s] = ft[s] + torch.randn(n, 6, generator=g, dtype=DT) * 0.1
    c = tc.Contacts(C_LINKS, C_KINDS, pos)
    out = est.estimate(q, qd, qdd, ft, c, ft_covariance=sig, backend=backend)
    # the unweighted references in eager: one kernel build for the cpu case (the suite's time)
    plain = est.estimate(q, qd, qdd, ft, c, ft_covariance=sig, weighted=False, backend="eager")
    A, r0, B, col_slot = build_A(est, q, qd, qdd, C_LINKS, C_KINDS, pos, dirs)
    blocks = region_blocks(est, C_LINKS, col_slot)
    b = stack_ft(est, ft) - r0
    w_est = torch.cat((out.force, out.moment), -1).numpy()
    for i in range(n):
        x, cov_x = _weighted_reference(
            A[i], b[i], blocks, {s: v[i].numpy() for s, v in sig.items()}
        )
        np.testing.assert_allclose(w_est[i], np.einsum("kju,u->kj", B[i], x), atol=ATOL, rtol=0)
        cov_w = np.einsum("kau,uv,kbv->kab", B[i], cov_x, B[i])
        scale = np.abs(cov_w).max()
        np.testing.assert_allclose(out.covariance[i].numpy(), cov_w, atol=1e-9 * scale, rtol=0)
        for s, (rows, cols) in blocks.items():  # the residual stays |A x - b|, unweighted
            res = np.linalg.norm(A[i][np.ix_(rows, cols)] @ x[cols] - b[i][rows])
            np.testing.assert_allclose(float(out.residual[s][i]), res, atol=ATOL, rtol=0)
    assert out.rank["r_arm_ft"].tolist() == [5] * n and out.rank["l_arm_ft"].tolist() == [6] * n
    # weighting changes the estimate where the readings conflict (r_arm: rank 5 of 6 rows)
    assert (out.force[:, 2:] - plain.force[:, 2:]).abs().max() > 1e-3
    # weighted=False is the paper's pinv, the noise only propagated
    ref = est.estimate(q, qd, qdd, ft, c, backend="eager")
    torch.testing.assert_close(plain.force, ref.force, atol=ATOL, rtol=0)


def test_weighted_torque_rows_get_their_own_noise(arms):
    """Measured joint torques weigh by ``tau_variance`` against the F/T rows."""
    model, est = arms
    n = 3
    links, kinds = ["l_forearm", "l_hand"], ["force", "force"]
    q, qd, qdd = random_state(model, n, seed=120)
    pos, dirs, wr = random_contacts(links, kinds, n, seed=121)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(links, ["known"] * 2, pos, wrenches=wr))
    g = torch.Generator().manual_seed(122)
    f_ext = torch.stack([fext_of(model, links, pos[i], wr[i]) for i in range(n)])
    tau = model.inverse_dynamics(q, qd, qdd, f_ext=f_ext)
    tau = tau + 0.05 * torch.randn(tau.shape, generator=g, dtype=DT)
    mask = torch.tensor([j.startswith(("l_elbow", "l_wrist")) for j in model.joint_names])
    var = torch.linspace(1e-3, 1e-2, model.nv, dtype=DT)
    sig = {s: torch.diag(torch.tensor([0.01] * 3 + [2.5e-5] * 3, dtype=DT)) for s in ft}
    for s in ft:
        ft[s] = ft[s] + torch.randn(n, 6, generator=g, dtype=DT) * 0.1
    c = tc.Contacts(links, kinds, pos)
    out = est.estimate(q, qd, qdd, ft, c, tau_measured=tau, tau_mask=mask, ft_covariance=sig,
                       tau_variance=var, backend="eager")  # fmt: skip
    # reference: A's torque rows from the torques the unit forces cause (linear in the forces)
    A, r0, B, col_slot = build_A(est, q, qd, qdd, links, kinds, pos, dirs)
    coords = np.flatnonzero(mask.numpy())
    rows6 = np.arange(6)  # l_arm_ft's rows
    for i in range(n):
        T = np.zeros((len(coords), A.shape[2]))
        for j in range(A.shape[2]):
            w = torch.as_tensor(B[i, :, :, j])
            fe = fext_of(model, links, pos[i], w).unsqueeze(0)
            zero = model.inverse_dynamics(q[i : i + 1], qd[i : i + 1], qdd[i : i + 1])
            with_f = model.inverse_dynamics(q[i : i + 1], qd[i : i + 1], qdd[i : i + 1], f_ext=fe)
            T[:, j] = (with_f - zero)[0, coords].numpy()
        tau0 = model.inverse_dynamics(q[i : i + 1], qd[i : i + 1], qdd[i : i + 1])[0, coords]
        Af = np.vstack([A[i][rows6], -T])
        bf = np.concatenate(
            [(stack_ft(est, ft)[i] - r0[i])[rows6], (tau[i, coords] - tau0).numpy() * -1]
        )
        S = np.zeros((6 + len(coords),) * 2)
        S[:6, :6] = sig["l_arm_ft"].numpy()
        S[6:, 6:] = np.diag(var.numpy()[coords])
        L = np.linalg.cholesky(S)
        x = np.linalg.lstsq(np.linalg.solve(L, Af), np.linalg.solve(L, bf), rcond=1e-7)[0]
        np.testing.assert_allclose(torch.cat((out.force, out.moment), -1)[i].numpy(),
                                   np.einsum("kju,u->kj", B[i], x), atol=ATOL, rtol=0)  # fmt: skip
    assert out.rank["l_arm_ft"].tolist() == [6] * n


def test_bad_noise_is_one_clear_error(arms):
    model, est = arms
    q, qd, qdd = random_state(model, 2, seed=130)
    ft = {s: torch.zeros(2, 6, dtype=DT) for s in est.sensor_names}
    c = tc.Contacts(["l_hand"], ["force"], torch.zeros(2, 1, 3, dtype=DT))
    good = torch.eye(6, dtype=DT) * 0.01
    cases = [
        ({"l_arm_ft": good}, "missing sensors \\['r_arm_ft'\\]"),
        ({"l_arm_ft": good, "r_arm_ft": good + torch.triu(torch.ones(6, 6, dtype=DT), 1)},
         "ft_covariance\\['r_arm_ft'\\] is not symmetric"),
        ({"l_arm_ft": good, "r_arm_ft": torch.diag(torch.tensor([1.0, 1, 1, 1, 1, -1e-3],
                                                                dtype=DT))},
         "ft_covariance\\['r_arm_ft'\\] is not positive definite: smallest eigenvalue -0.001"),
        ({"l_arm_ft": good, "r_arm_ft": good, "l_foot_ft": good}, "unknown or unused sensors"),
        ({"l_arm_ft": good, "r_arm_ft": good[:5, :5]}, "must have shape \\(6, 6\\)"),
    ]  # fmt: skip
    for cov, msg in cases:
        with pytest.raises(tc.errors.InputError, match=msg):
            est.estimate(q, qd, qdd, ft, c, ft_covariance=cov)
    cov = {"l_arm_ft": good, "r_arm_ft": good}
    tau = torch.zeros(2, model.nv, dtype=DT)
    with pytest.raises(tc.errors.InputError, match="tau_variance is needed"):
        est.estimate(q, qd, qdd, ft, c, ft_covariance=cov, tau_measured=tau)
    with pytest.raises(tc.errors.InputError, match="tau_variance must be > 0"):
        est.estimate(q, qd, qdd, ft, c, ft_covariance=cov, tau_measured=tau,
                     tau_variance=torch.zeros(model.nv, dtype=DT))  # fmt: skip
    # a partial covariance is fine when only propagated
    r = est.estimate(q, qd, qdd, ft, c, ft_covariance={"l_arm_ft": good}, weighted=False)
    assert r.covariance.shape == (2, 1, 6, 6)
