"""Friction-cone constrained estimation (torchcontact.constrained) against clarabel and physics.

Reference: clarabel (an interior-point conic solver, test dependency) on the same problem
``min 1/2 |A x - b|^2 + eps/2 |x|^2`` s.t. ``C_k x_k in Q^3``, at tolerances 1e-12. Agreement is
checked to 1e-6 relative where clarabel reports ``Solved``; on every problem our objective must be
no worse than clarabel's and our forces inside their cones.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from robots import load_model, random_state

import torchcontact as tc
from torchcontact.constrained import FrictionCones, PreviousFrame, cone_constrained_lstsq
from torchcontact.errors import InputError

REF_RTOL = 1e-6  # constrained solution vs clarabel, relative to max(1, |x|)
MU = math.tan(0.5)


MIN_NORM = FrictionCones(objective="min_norm")


def _cone_C(n, mu):
    n = n / np.linalg.norm(n)
    t1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    t1 /= np.linalg.norm(t1)
    return np.stack([-mu * n, t1, np.cross(n, t1)])


def _clarabel(A, b, Cs, eps):
    import clarabel
    import scipy.sparse as sps

    u = A.shape[1]
    P = A.T @ A + eps * np.eye(u)
    G = np.zeros((3 * len(Cs), u))
    for k, C in enumerate(Cs):
        G[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = -C
    st = clarabel.DefaultSettings()
    st.verbose = False
    st.tol_gap_abs = st.tol_gap_rel = st.tol_feas = 1e-12
    st.tol_ktratio = 1e-10
    st.static_regularization_constant = 1e-12
    st.iterative_refinement_reltol = st.iterative_refinement_abstol = 1e-15
    st.iterative_refinement_max_iter = 50
    st.equilibrate_enable = False
    st.max_iter = 500
    cones = [clarabel.SecondOrderConeT(3)] * len(Cs)
    solver = clarabel.DefaultSolver(
        sps.csc_matrix(np.triu(P)), -A.T @ b, sps.csc_matrix(G), np.zeros(3 * len(Cs)), cones, st
    )
    r = solver.solve()
    return np.array(r.x), str(r.status)


def _random_problems(rng, n, K, R, feasible):
    As, bs, Cs = [], [], []
    for _ in range(n):
        # well conditioned (singular values in [0.3, 3]), so that clarabel's 1e-12 gap pins x
        U, _ = np.linalg.qr(rng.normal(size=(R, 3 * K)))
        V, _ = np.linalg.qr(rng.normal(size=(3 * K, 3 * K)))
        A = U @ np.diag(rng.uniform(0.3, 3.0, size=3 * K)) @ V.T
        ns = [v / np.linalg.norm(v) for v in rng.normal(size=(K, 3))]
        if feasible == "apex":  # some forces pull: their estimates sit at the cones' apexes
            f = [nk * rng.uniform(1, 10) * (1 if rng.random() < 0.5 else -1) for nk in ns]
            b = A @ np.concatenate(f)
        elif feasible:  # forces pushing inside their cones: the unconstrained solution is feasible
            f = []
            for nk in ns:
                t = rng.normal(size=3)
                t -= t.dot(nk) * nk
                f.append(-nk * rng.uniform(1, 10) + 0.3 * t)
            b = A @ np.concatenate(f)
        else:  # arbitrary readings: most frames have active cones
            b = rng.normal(size=R) * 10
        As.append(A)
        bs.append(b)
        Cs.append([_cone_C(nk, MU) for nk in ns])
    return As, bs, Cs


@pytest.mark.parametrize("K,R", [(2, 6), (2, 9), (3, 9), (4, 12), (6, 18)])
@pytest.mark.parametrize("feasible", [True, False, "apex"])
def test_matches_clarabel(K, R, feasible):
    rng = np.random.default_rng(10 * K + R + (2 if feasible == "apex" else feasible))
    n, eps = 80, 1e-9
    As, bs, Cs = _random_problems(rng, n, K, R, feasible)
    cones = [(range(3 * k, 3 * k + 3), torch.tensor(np.stack([c[k] for c in Cs])))
             for k in range(K)]  # fmt: skip
    x, ok, it, act = cone_constrained_lstsq(
        torch.tensor(np.stack(As)), torch.tensor(np.stack(bs)), cones,
        settings=FrictionCones(eps=eps),
    )  # fmt: skip
    # every frame stopped within the budget (gap at rounding level): converged
    assert ok.all() and (it <= FrictionCones().iterations).all()
    x = x.numpy()
    solved = 0
    for i in range(n):
        ref, status = _clarabel(As[i], bs[i], Cs[i], eps)

        def obj(v, i=i):
            return 0.5 * np.sum((As[i] @ v - bs[i]) ** 2) + 0.5 * eps * v @ v

        # no worse than the reference (clarabel may sit 1e-12 outside a cone: 1e-10 slack)
        assert obj(x[i]) <= obj(ref) + 1e-10 * (1 + obj(ref))
        for k in range(K):  # inside every cone
            s = Cs[i][k] @ x[i][3 * k : 3 * k + 3]
            assert s[0] >= np.hypot(s[1], s[2]) - 1e-9 * (1 + abs(s[0]))
        if status == "Solved":  # AlmostSolved (1e-8 met, not 1e-12) is off by up to 3e-4
            solved += 1
            np.testing.assert_allclose(x[i], ref, atol=REF_RTOL * max(1, np.abs(ref).max()))
    assert solved >= 1  # clarabel solves 1 to 80 of 80 at 1e-12, fewest with six active cones
    if feasible == "apex":  # a pulling force's estimate is at its apex: active, about zero
        assert 0.3 < act.float().mean() < 0.9
    elif feasible:
        assert act.float().mean() < 0.1  # forces strictly inside: (almost) no cone binds
    else:
        assert act.float().mean() > 0.5


def _icub_two_pushes(n, seed, boundary=False):
    """Two pushing forces on the iCub left forearm (rank 5 of 6) and their noise-free readings."""
    model = load_model("icub")
    est = tc.ContactEstimator(model)
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    q, qd, qdd = random_state(model, n, seed=seed)
    pos = (torch.rand(n, 2, 3, generator=g, dtype=f64) - 0.5) * torch.tensor(
        [0.03, 0.03, 0.1], dtype=f64
    )
    if boundary:
        # both forces on their cones' boundaries, tilted along u = c2 - c1 (normals orthogonal
        # to u): moving along the unobservable direction (u, -u) leaves one cone either way
        u = pos[:, 1] - pos[:, 0]
        u = u / u.norm(dim=-1, keepdim=True)
        n0 = torch.linalg.cross(u, torch.randn(n, 3, generator=g, dtype=f64))
        n0 = n0 / n0.norm(dim=-1, keepdim=True)
        normals = n0.unsqueeze(1).expand(n, 2, 3).contiguous()
        mag = 1 + 9 * torch.rand(n, 2, 1, generator=g, dtype=f64)
        force = mag * (-math.cos(0.5) * normals + math.sin(0.5) * u.unsqueeze(1))
    else:
        normals = torch.randn(n, 2, 3, generator=g, dtype=f64)
        normals = normals / normals.norm(dim=-1, keepdim=True)
        t = torch.randn(n, 2, 3, generator=g, dtype=f64)
        t = t - (t * normals).sum(-1, keepdim=True) * normals
        t = t / t.norm(dim=-1, keepdim=True)
        ang = 0.5 * torch.rand(n, 2, 1, generator=g, dtype=f64)
        force = (
            10
            * torch.rand(n, 2, 1, generator=g, dtype=f64)
            * (-torch.cos(ang) * normals + torch.sin(ang) * t)
        )
    links = ("l_forearm", "l_forearm")
    known = tc.Contacts(links, ("known",) * 2, pos, wrenches=torch.cat([force, 0 * force], -1))
    ft = est.predict_ft(q, qd, qdd, known)
    contacts = tc.Contacts(links, ("force",) * 2, pos, normals=normals, cone_angle=0.5)
    return est, (q, qd, qdd, ft), contacts, force


def test_recovers_the_truth_where_the_cones_make_it_identifiable():
    """The minimum-norm objective: forces on the cones' boundaries are reached exactly."""
    est, state, contacts, truth = _icub_two_pushes(40, seed=1, boundary=True)
    free = est.estimate(*state, contacts, backend="eager")
    cone = est.estimate(*state, contacts, constraints=MIN_NORM, backend="eager")
    assert (free.rank["l_arm_ft"] == 5).all() and (free.nullity["l_arm_ft"] == 1).all()
    assert (free.force - truth).abs().max() > 0.05  # the pseudo-inverse cannot tell
    # the truth sits where two cone boundaries pinch the unobservable line: the multipliers are
    # only eps-sized there (weakly complementary), which costs the solver digits: 1e-5 relative
    torch.testing.assert_close(cone.force, truth, atol=1e-5 * truth.abs().max(), rtol=0)
    assert cone.cones.converged["l_arm_ft"].all()
    assert cone.cones.active.all()  # both forces on their cones' boundaries


def test_equals_pinv_when_the_unconstrained_solution_is_inside_the_cones():
    est, state, contacts, truth = _icub_two_pushes(60, seed=2)
    free = est.estimate(*state, contacts, backend="eager")
    # normals opposite to the pseudo-inverse forces: every unconstrained solution is inside
    inside = tc.Contacts(contacts.links, contacts.kinds, contacts.positions,
                         normals=-free.force, cone_angle=0.5)  # fmt: skip
    cone = est.estimate(*state, inside, constraints=MIN_NORM, backend="eager")
    torch.testing.assert_close(cone.force, free.force, atol=1e-6 * truth.abs().max(), rtol=0)
    torch.testing.assert_close(cone.joint_torques, free.joint_torques, atol=1e-5, rtol=0)
    assert not cone.cones.active.any()
    # with arbitrary normals the cones bind in some frames and the error to the truth drops
    tight = est.estimate(*state, contacts, constraints=MIN_NORM, backend="eager")
    assert tight.cones.active.any()
    err_free = (free.force - truth).norm(dim=-1).median()
    err_cone = (tight.force - truth).norm(dim=-1).median()
    assert err_cone < err_free


def test_warm_start_kernel_and_nullspace():
    """Generated kernel vs eager, warm start, null-space basis (bundled arm: a small kernel)."""
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    est = tc.ContactEstimator(model)
    n, f64 = 37, torch.float64
    g = torch.Generator().manual_seed(3)
    q, qd, qdd = random_state(model, n, seed=3)
    pos = 0.05 * torch.randn(n, 2, 3, generator=g, dtype=f64)
    normals = torch.randn(n, 2, 3, generator=g, dtype=f64)
    force = -3 * normals + torch.randn(n, 2, 3, generator=g, dtype=f64)
    links = ("forearm_skin", "hand_skin")
    wr = torch.cat([force, 0 * force], -1)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(links, ("known",) * 2, pos, wrenches=wr))
    c = tc.Contacts(links, ("force",) * 2, pos, normals=normals, friction=0.6)
    cons = FrictionCones()
    eager = est.estimate(q, qd, qdd, ft, c, constraints=cons, nullspace=True, backend="eager")
    kern = est.estimate(q, qd, qdd, ft, c, constraints=cons, nullspace=True, backend="cpu")
    scale = force.abs().max()
    torch.testing.assert_close(kern.force, eager.force, atol=1e-7 * scale, rtol=0)
    assert torch.equal(kern.cones.active, eager.cones.active)
    assert kern.cones.converged["base_ft"].all()
    # null space: orthonormal basis of dimension unknowns - rank, spanning what the sensor
    # cannot see (the same projector from both backends)
    N = eager.nullspace["base_ft"]
    d = eager.nullity["base_ft"]
    assert (d == 6 - eager.rank["base_ft"]).all() and (d == 0).any() is not None
    cols = N.norm(dim=-2) > 0.5
    assert torch.equal(cols.sum(-1), d)
    proj = N @ N.transpose(-1, -2)
    torch.testing.assert_close(proj, kern.nullspace["base_ft"] @ kern.nullspace["base_ft"].mT,
                               atol=1e-9, rtol=0)  # fmt: skip
    i = int(torch.argmax(d))
    if int(d[i]) > 0:
        v = N[i, :, 0].reshape(2, 3)  # forces that add no reading
        w = torch.cat([v, 0 * v], -1).unsqueeze(0)
        sl = (slice(i, i + 1),)
        zero = tc.Contacts(links, ("known",) * 2, pos[sl], wrenches=0 * w)
        moved = tc.Contacts(links, ("known",) * 2, pos[sl], wrenches=w)
        a = est.predict_ft(q[sl], qd[sl], qdd[sl], moved)["base_ft"]
        b = est.predict_ft(q[sl], qd[sl], qdd[sl], zero)["base_ft"]
        torch.testing.assert_close(a, b, atol=1e-9, rtol=0)
    # warm start from the solution: same answer, converged at once; NaN falls back to pinv
    warm = est.estimate(q, qd, qdd, ft, c, constraints=cons, backend="eager",
                        warm_start=(eager.force, eager.moment))  # fmt: skip
    torch.testing.assert_close(warm.force, eager.force, atol=1e-6 * scale, rtol=0)
    assert warm.cones.iterations["base_ft"].float().mean() <= (
        eager.cones.iterations["base_ft"].float().mean()
    )
    nan = torch.full_like(eager.force, float("nan"))
    cold = est.estimate(q, qd, qdd, ft, c, constraints=cons, backend="eager",
                        warm_start=(nan, nan))  # fmt: skip
    torch.testing.assert_close(cold.force, eager.force, atol=1e-9 * scale, rtol=0)


@pytest.mark.parametrize("shape", [(), (1,), (3,), (2, 3)])
def test_batch_shapes_and_float32(shape):
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    est = tc.ContactEstimator(model)
    g = torch.Generator().manual_seed(4)
    n = math.prod(shape)
    q, qd, qdd = (x.reshape(*shape, model.nv) for x in random_state(model, n, seed=4))
    pos = 0.05 * torch.randn(*shape, 2, 3, generator=g, dtype=torch.float64)
    normals = torch.randn(*shape, 2, 3, generator=g, dtype=torch.float64)
    ft = {"base_ft": 5 * torch.randn(*shape, 6, generator=g, dtype=torch.float64)}
    links = ("forearm_skin", "hand_skin")
    c = tc.Contacts(
        links, ("force", "wrench"), pos, normals=normals, friction=torch.tensor([0.5, 1])
    )
    r = est.estimate(q, qd, qdd, ft, c, constraints=FrictionCones(), backend="eager")
    assert r.force.shape == (*shape, 2, 3) and r.cones.active.shape == (*shape, 2)
    assert r.cones.iterations["base_ft"].shape == shape
    if n > 1:  # batched equals a loop over frames; frames differ
        flat = r.force.reshape(n, 2, 3)
        one = est.estimate(q.reshape(n, -1)[:1], qd.reshape(n, -1)[:1], qdd.reshape(n, -1)[:1],
                           {"base_ft": ft["base_ft"].reshape(n, 6)[:1]},
                           tc.Contacts(links, c.kinds, pos.reshape(n, 2, 3)[:1],
                                       normals=normals.reshape(n, 2, 3)[:1],
                                       friction=c.friction),
                           constraints=FrictionCones(), backend="eager")  # fmt: skip
        torch.testing.assert_close(one.force[0], flat[0], atol=1e-9, rtol=0)
        assert not torch.allclose(flat[0], flat[-1])
    # float32: same cones, same answer to float32 accuracy (the default objective in float32 is
    # the minimum-norm one: FrictionCones.objective_of)
    r = est.estimate(q, qd, qdd, ft, c, constraints=MIN_NORM, backend="eager")
    m32 = model.to(dtype=torch.float32)
    est32 = tc.ContactEstimator(m32)
    c32 = tc.Contacts(links, c.kinds, pos.float(), normals=normals.float(),
                      friction=torch.tensor([0.5, 1.0]))  # fmt: skip
    r32 = est32.estimate(q.float(), qd.float(), qdd.float(), {"base_ft": ft["base_ft"].float()},
                         c32, constraints=FrictionCones(), backend="eager")  # fmt: skip
    assert r32.force.dtype == torch.float32
    scale = max(1.0, float(r.force.abs().max()))
    torch.testing.assert_close(r32.force.double(), r.force, atol=2e-2 * scale, rtol=0)


def test_bad_input_is_rejected_with_a_clear_error():
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    est = tc.ContactEstimator(model)
    q = torch.zeros(2, model.nv, dtype=torch.float64)
    ft = {"base_ft": torch.ones(2, 6, dtype=torch.float64)}
    pos = torch.zeros(2, 1, 3, dtype=torch.float64)
    normals = torch.tensor([[[0, 0, 1.0]], [[0, 0, 0.0]]], dtype=torch.float64)
    cons = FrictionCones()
    with pytest.raises(InputError, match="zero normal on pushing slot 0 .* frame 1"):
        est.estimate(q, q, q, ft, tc.Contacts(["hand_skin"], ["force"], pos, normals=normals,
                                              friction=0.5), constraints=cons)  # fmt: skip
    with pytest.raises(ValueError, match="friction must be a finite number > 0"):
        tc.Contacts(["hand_skin"], ["force"], pos, friction=-0.2)
    with pytest.raises(InputError, match="friction coefficient -0.2"):
        est.estimate(q, q, q, ft, tc.Contacts(["hand_skin"], ["force"], pos, normals=normals + 1,
                                              friction=torch.tensor([-0.2])), constraints=cons)  # fmt: skip
    with pytest.raises(ValueError, match="cone_angle must be in"):
        tc.Contacts(["hand_skin"], ["force"], pos, cone_angle=2.0)
    with pytest.raises(ValueError, match="not both"):
        tc.Contacts(["hand_skin"], ["force"], pos, friction=0.5, cone_angle=0.5)
    with pytest.raises(InputError, match="need contacts.normals"):
        est.estimate(q, q, q, ft, tc.Contacts(["hand_skin"], ["force"], pos, friction=0.5),
                     constraints=cons)  # fmt: skip
    with pytest.raises(InputError, match="need contacts.friction"):
        est.estimate(q, q, q, ft, tc.Contacts(["hand_skin"], ["force"], pos, normals=normals + 1),
                     constraints=cons)  # fmt: skip
    with pytest.raises(InputError, match="iterations"):
        FrictionCones(iterations=0)
    # a non-pushing or inactive slot needs no normal; a force_dir slot pushes without one
    c = tc.Contacts(["hand_skin", "hand_skin"], ["force", "force_dir"], pos.expand(2, 2, 3),
                    directions=torch.tensor([0, 0, -1.0]).expand(2, 2, 3).double(),
                    pushing=torch.tensor([False, True]))  # fmt: skip
    r = est.estimate(q, q, q, ft, c, constraints=cons, backend="eager")
    assert (r.status == 0).all() and r.cones.converged["base_ft"].all()
    # NaN normals are per-frame data errors: status, not an exception
    bad = torch.tensor([[[0, 0, 1.0]], [[float("nan"), 0, 1.0]]], dtype=torch.float64)
    r = est.estimate(q, q, q, ft, tc.Contacts(["hand_skin"], ["force"], pos, normals=bad,
                                              friction=0.5), constraints=cons, backend="eager")  # fmt: skip
    assert r.status.tolist() == [0, 4] and torch.isnan(r.force[1]).all()


@pytest.mark.parametrize(
    "case", ["empty", "all inactive", "all not pushing", "all known", "all NaN normals",
             "one valid"]
)  # fmt: skip
def test_slot_list_edge_cases_take_the_unconstrained_path(case):
    """Slots without a cone to keep run like the pseudo-inverse (issue 19, item 5).

    An empty slot list once built ``torch.tensor([])`` as float, then ``bool & float`` failed.
    Frames whose slots have no valid pushing contact take the unconstrained path: the same
    forces, torques and status as without ``constraints``, converged with 0 iterations.
    """
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    est = tc.ContactEstimator(model, backend="eager")
    n, f64 = 5, torch.float64
    g = torch.Generator().manual_seed(5)
    q, qd, qdd = random_state(model, n, seed=5)
    ft = {"base_ft": 5 * torch.randn(n, 6, generator=g, dtype=f64)}
    links, kinds = ("forearm_skin", "hand_skin"), ("force", "force")
    pos = 0.05 * torch.randn(n, 2, 3, generator=g, dtype=f64)
    normals = torch.randn(n, 2, 3, generator=g, dtype=f64)
    kw: dict = {"normals": normals, "friction": 0.5}
    if case == "empty":
        links, kinds, pos, kw = (), (), pos[:, :0], {}
    elif case == "all inactive":
        kw["active"] = torch.zeros(n, 2, dtype=torch.bool)
    elif case == "all not pushing":
        kw["pushing"] = torch.tensor([False, False])
    elif case == "all known":
        kinds = ("known", "known")
        kw["wrenches"] = torch.randn(n, 2, 6, generator=g, dtype=f64)
    elif case == "all NaN normals":
        kw["normals"] = torch.full_like(normals, float("nan"))
    else:  # one valid pushing slot beside an inactive one
        kw["active"] = torch.tensor([[True, False]]).expand(n, 2)
    c = tc.Contacts(links, kinds, pos, **kw)
    free = est.estimate(q, qd, qdd, ft, c)
    for warm in (None, PreviousFrame(None, 2)):
        cone = est.estimate(q, qd, qdd, ft, c, constraints=FrictionCones(), warm_start=warm)
        assert cone.force.shape == (n, len(links), 3)
        if case == "all NaN normals":  # a data error of every frame: status 4, NaN outputs
            assert (cone.status == 4).all() and torch.isnan(cone.force).all()
            continue
        assert torch.equal(cone.status, free.status)
        assert (cone.status == 0).all() and cone.cones.converged["base_ft"].all()
        if case == "one valid":  # the active slot's force is in its cone, the other one is 0
            f, nrm = cone.force[:, 0], normals[:, 0] / normals[:, 0].norm(dim=-1, keepdim=True)
            push = -(f * nrm).sum(-1)
            tangent = (f + push[:, None] * nrm).norm(dim=-1)
            assert (push >= -1e-9).all() and (tangent <= 0.5 * push + 1e-6).all()
            assert (cone.force[:, 1] == 0).all() and not cone.cones.active[:, 1].any()
            continue
        assert (cone.cones.iterations["base_ft"] == 0).all() and not cone.cones.active.any()
        torch.testing.assert_close(cone.force, free.force, atol=1e-9, rtol=0)
        torch.testing.assert_close(cone.joint_torques, free.joint_torques, atol=1e-9, rtol=0)


# ------------------------------------------------------------------ the MAP objective (ForcePrior)
def _tcarm_pushes(n, seed, weighted):
    """Two pushing forces on the bundled arm (rank 5 of 6 unknowns), noisy readings."""
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    est = tc.ContactEstimator(model)
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    q, qd, qdd = random_state(model, n, seed=seed)
    pos = 0.05 * torch.randn(n, 2, 3, generator=g, dtype=f64)
    normals = torch.randn(n, 2, 3, generator=g, dtype=f64)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    force = -5 * normals + torch.randn(n, 2, 3, generator=g, dtype=f64)
    links = ("forearm_skin", "hand_skin")
    wr = torch.cat([force, 0 * force], -1)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(links, ("known",) * 2, pos, wrenches=wr))
    sig = torch.tensor([0.1, 0.2, 0.1, 0.005, 0.004, 0.006], dtype=f64)
    ft["base_ft"] = ft["base_ft"] + sig * torch.randn(n, 6, generator=g, dtype=f64)
    c = tc.Contacts(links, ("force",) * 2, pos, normals=normals, cone_angle=0.5)
    kw = {"ft_covariance": {"base_ft": torch.diag(sig**2)}} if weighted else {}
    # A (n, 6, 6) column by column (linear in the forces) and the contact-free reading
    zero = tc.Contacts(links, ("known",) * 2, pos, wrenches=0 * wr)
    r0 = est.predict_ft(q, qd, qdd, zero)["base_ft"]
    A = torch.zeros(n, 6, 6, dtype=f64)
    for j in range(6):
        w = torch.zeros(n, 2, 6, dtype=f64)
        w[:, j // 3, j % 3] = 1.0
        A[:, :, j] = est.predict_ft(q, qd, qdd, tc.Contacts(links, ("known",) * 2, pos,
                                                            wrenches=w))["base_ft"] - r0  # fmt: skip
    W = 1 / sig if weighted else torch.full((6,), 1 / 0.01, dtype=f64)  # unweighted_sigma
    return (
        est,
        (q, qd, qdd, ft),
        c,
        kw,
        (A * W[:, None]).numpy(),
        ((ft["base_ft"] - r0) * W).numpy(),
    )


@pytest.mark.parametrize("weighted", [True, False])
def test_map_is_the_minimiser_of_the_stated_posterior(weighted):
    """The default objective: the gradient of the documented negative log-posterior vanishes at
    the estimate (a strictly convex function: it is its unique minimiser), computed in numpy."""
    est, state, c, kw, A, b = _tcarm_pushes(24, seed=11, weighted=weighted)
    r = est.estimate(*state, c, constraints=FrictionCones(), backend="eager", **kw)
    assert r.cones.converged["base_ft"].all() and (r.status == 0).all()
    x = r.force.reshape(-1, 6).numpy()
    n_hat = c.normals.numpy()
    eps, nu = 1e-9, tc.ForcePrior().nu
    for i in range(len(x)):
        x_pinv = np.linalg.pinv(A[i], rcond=1e-7) @ b[i]
        lam = 1.0 / (x_pinv @ x_pinv / 2 + 1e-6) + eps  # ForcePrior(): relative 1, 2 slots
        grad = A[i].T @ (A[i] @ x[i] - b[i]) + lam * x[i]
        for k in range(2):
            C = _cone_C(n_hat[i, k], MU)
            y = C @ x[i, 3 * k : 3 * k + 3]
            assert y[0] > np.hypot(y[1], y[2])  # strictly inside its cone
            jy = y * np.array([1.0, -1.0, -1.0])
            grad[3 * k : 3 * k + 3] -= nu * C.T @ jy / (y @ jy)  # d (nu / 2 log(y^T J y))
        scale = np.abs(A[i].T @ b[i]).max() + 1.0
        assert np.abs(grad).max() < 1e-7 * scale, (i, grad)
    # the prior moves the estimate away from the minimum-norm one, towards the truth's depth
    mn = est.estimate(*state, c, constraints=MIN_NORM, backend="eager", **kw)
    assert (mn.force - r.force).abs().max() > 0.1


def test_unconverged_frames_get_status_256_and_a_warm_start_restarts():
    est, state, c, kw, _, _ = _tcarm_pushes(24, seed=12, weighted=True)
    cold = est.estimate(*state, c, constraints=FrictionCones(), backend="eager", **kw)
    assert cold.cones.converged["base_ft"].all() and (cold.status == 0).all()
    # a budget too small: not converged, status 256 (a warning: outputs finite), never ok
    short = est.estimate(*state, c, constraints=FrictionCones(iterations=2), backend="eager",
                         **kw)  # fmt: skip
    unconv = ~short.cones.converged["base_ft"]
    assert unconv.sum() > 5
    assert torch.equal(short.status != 0, unconv) and (short.status[unconv] == 256).all()
    assert short.force.isfinite().all()
    assert tc.status_messages(256).startswith("constrained solve not converged")
    # a hopeless warm start (every force pulling: the answer reversed) runs out of budget,
    # restarts from the pseudo-inverse and ends where the cold start does (forces of 1e6 N no
    # longer do: the MAP objective's warm start at that scale converges in 6 to 11 iterations)
    far = (-cold.force, torch.zeros_like(cold.moment))
    warm = est.estimate(*state, c, constraints=FrictionCones(), warm_start=far, backend="eager",
                        **kw)  # fmt: skip
    assert warm.cones.converged["base_ft"].all() and (warm.status == 0).all()
    assert (warm.cones.iterations["base_ft"] > 25).any()  # the restart ran
    scale = float(cold.force.abs().max())
    torch.testing.assert_close(warm.force, cold.force, atol=1e-6 * scale, rtol=0)
    kern = est.estimate(*state, c, constraints=FrictionCones(), warm_start=far, backend="cpu",
                        **kw)  # fmt: skip
    torch.testing.assert_close(kern.force, cold.force, atol=1e-6 * scale, rtol=0)
