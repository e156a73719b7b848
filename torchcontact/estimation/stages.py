"""The stages of the estimator, each a pure function on scalars (:mod:`torchcontact._scalar`).

See :mod:`torchcontact.estimation` for the equations. Every function takes the frozen
:class:`~torchcontact.estimation.layout.EstimationModel` and per-frame scalars (constants, ``(N,)``
tensors or traced symbols) and returns new scalars; :mod:`torchcontact.estimation.programs`
chains them into one program per layout, run eagerly or compiled into a kernel.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

from torchcontact import dynamics as _dyn
from torchcontact import spatial as sp
from torchcontact._scalar import Scalar, add, div, gt, is_const, mul, neg, select, sqrt, sub, sum_
from torchcontact.estimation.layout import EstimationModel, Region, Slot
from torchcontact.solve import (
    Factorization,
    factorize,
    solve_factored,
    tril_solve,
    triu_t_solve,
)

__all__ = [
    "SlotMap",
    "backward",
    "body_in_sensor",
    "contact_point",
    "contact_maps",
    "contact_matrix",
    "contact_wrenches",
    "covariance",
    "forward",
    "nullspace_basis",
    "region_rhs",
    "wrench_on_body",
]


def forward(
    em: EstimationModel,
    q: list[Scalar],
    qd: list[Scalar],
    qdd: list[Scalar],
    base: dict[str, list[Scalar]] | None,
):
    """Stage 1, the forward pass: ``X`` (joint placements), ``v``, ``a`` and body wrenches ``f``.

    All per body, in internal frames (:mod:`torchcontact.dynamics`).
    """
    tree = em.tree
    X = _dyn.joint_placements(tree, q)
    v, a, f = _dyn.rnea_forward(tree, X, qd, qdd, _dyn.root_motion(tree, base))
    return X, v, a, f


def contact_point(slot: Slot, pos: Sequence[Scalar]) -> sp.V3:
    """A contact point given in the slot's link frame, in the body's internal frame."""
    return sp.v_add(sp.m_vec(slot.R, tuple(pos)), slot.p)


def wrench_on_body(slot: Slot, c_b: sp.V3, w: sp.Force) -> sp.Force:
    """A contact wrench (link frame, about the point) on the body (internal frame, origin)."""
    f = sp.m_vec(slot.R, w[0])
    return f, sp.v_add(sp.m_vec(slot.R, w[1]), sp.v_cross(c_b, f))


def _sensor_wrench_in_child(reg: Region, reading: Sequence[Scalar]) -> sp.Force:
    """A reading (sensor frame, its sign applied) in the child body's internal frame."""
    W = (tuple(mul(reg.sign, x) for x in reading[:3]), tuple(mul(reg.sign, x) for x in reading[3:]))
    return sp.force_to_parent(reg.T_child_sensor, W)


def region_rhs(
    em: EstimationModel,
    X: list,
    f: list,
    readings: Sequence[Sequence[Scalar]],
    known: dict[int, list[sp.Force]],
    tau_meas: Sequence[Scalar] | None,
    tau_mask: Sequence[Scalar] | None,
):
    """Stage 2: the right side ``b`` of every region and the torques before the contacts.

    One backward pass of the RNEA with the known contacts applied and every chosen sensor's
    measured wrench transmitted to the root side of its joint.

    Args:
        em: the estimation model.
        X: joint placements.
        f: body wrenches.
        readings: per sensor, its 6 reading scalars (sensor frame, declared direction).
        known: body -> known contact wrenches on it (internal frame, about the body origin).
        tau_meas: ``nv`` measured joint torques, or None.
        tau_mask: ``nv`` 0/1 validity of each measurement, or None.

    Returns:
        ``(F, tau, b)``: per-body transmitted wrenches, the ``nv`` joint torques without the
        unknown contacts, and per region its right side (6 sensor rows, then one per torque
        coordinate).
    """
    tree = em.tree
    f_net = list(f)
    for body, ws in known.items():
        f_net[body] = (
            sp.v_sub(f[body][0], sp.v_sum([w[0] for w in ws])),
            sp.v_sub(f[body][1], sp.v_sum([w[1] for w in ws])),
        )
    W_child = [_sensor_wrench_in_child(reg, readings[i]) for i, reg in enumerate(em.regions)]
    F, tau = _dyn.backward_pass(
        tree, X, f_net, {reg.child: W_child[i] for i, reg in enumerate(em.regions)}
    )
    b = []
    for i, reg in enumerate(em.regions):
        Fs = sp.force_to_child(reg.T_child_sensor, F[reg.child])  # in the sensor frame
        rows = [sub(Fs[0][k], mul(reg.sign, readings[i][k])) for k in range(3)]
        rows += [sub(Fs[1][k], mul(reg.sign, readings[i][3 + k])) for k in range(3)]
        for c in reg.torque_coords if tau_meas is not None else ():
            rhs = sub(_coord_torque(tree, F, c), tau_meas[c])
            rows.append(mul(rhs, tau_mask[c]) if tau_mask is not None else rhs)
        b.append(rows)
    return F, tau, b


def _coord_torque(tree: _dyn.Tree, F: list, c: int) -> Scalar:
    terms = []
    for j, body in enumerate(tree.bodies):
        if body.coord == c:
            t = F[j][1][2] if body.kind == "revolute" else F[j][0][2]
            terms.append(mul(body.mult, t))
    return sum_(terms)


class SlotMap(NamedTuple):
    """What stage 3 keeps of one slot for stage 5.

    Attributes:
        R: rotation of the contact link frame in the sensor frame.
        c: contact point in the sensor frame, m.
        u: unit force direction in the sensor frame (``force_dir`` slots), else None.
        d: unit force direction in the link frame (``force_dir`` slots), else None.
        s: per torque row of the region, the joint-space coefficient (a twist in the sensor
            frame, zero when the slot is outside the row's joints' subtrees).
        active: the slot's 0/1 activity.
    """

    R: sp.M3
    c: sp.V3
    u: sp.V3 | None
    d: sp.V3 | None
    s: list
    active: Scalar


def _gram6(kind: str, c: sp.V3, u: sp.V3 | None) -> list[list[Scalar]]:
    """``A_k P_k A_k^T`` (6 x 6, sensor frame) of one slot from its point and direction."""
    if kind == "force_dir":
        cu = sp.v_cross(c, u)
        col = [*u, *cu]
        return [[mul(col[i], col[j]) for j in range(6)] for i in range(6)]
    # A = [R; C R] (force) or [[R, 0]; [C R, R]] (wrench) with C = [c]x, R R^T = 1:
    # A A^T = [[1, C^T]; [C, C C^T (+ 1 for a wrench)]], and C C^T = |c|^2 1 - c c^T
    C = ((0.0, neg(c[2]), c[1]), (c[2], 0.0, neg(c[0])), (neg(c[1]), c[0], 0.0))
    cc = sp.v_dot(c, c)
    G: list[list[Scalar]] = [[0.0] * 6 for _ in range(6)]
    for i in range(3):
        G[i][i] = 1.0
        for j in range(3):
            G[3 + i][j] = C[i][j]
            G[j][3 + i] = C[i][j]
            G[3 + i][3 + j] = sub(cc if i == j else 0.0, mul(c[i], c[j]))
        if kind == "wrench":
            G[3 + i][3 + i] = add(G[3 + i][3 + i], 1.0)
    return G


def contact_maps(
    em: EstimationModel,
    X: list,
    pos: Sequence[Sequence[Scalar]],
    dirs: Sequence[Sequence[Scalar]] | None,
    active: Sequence[Scalar],
    tau_mask: Sequence[Scalar] | None,
):
    """Stage 3: each slot's map to its sensor frame and every region's Gram matrix ``G``.

    Args:
        em: the estimation model.
        X: joint placements.
        pos: per slot, the contact point (3 scalars, link frame).
        dirs: per slot, the force direction (3 scalars, link frame; ``force_dir`` slots).
        active: per slot, 1 in contact, 0 not.
        tau_mask: ``nv`` 0/1 validity of each torque measurement, or None (no torque rows).

    Returns:
        ``(maps, G)``: per slot a :class:`SlotMap` (None for ``known`` slots), per region its
        ``R x R`` Gram matrix (lower triangle filled).
    """
    tree = em.tree
    maps: list[SlotMap | None] = [None] * len(em.slots)
    grams = []
    for r, reg in enumerate(em.regions):
        pose = body_in_sensor(em, X, r)
        rows = list(reg.torque_coords) if tau_mask is not None else []
        R = 6 + len(rows)
        G: list[list[Scalar]] = [[0.0] * R for _ in range(R)]
        for k in reg.slots:
            slot = em.slots[k]
            if slot.kind == "known":
                continue
            Rb, pb = pose(slot.body)
            R_sk = sp.m_mul(Rb, slot.R)
            c = sp.pose_apply((Rb, pb), contact_point(slot, pos[k]))
            u = d = None
            if slot.kind == "force_dir":
                d = _unit(dirs[k])
                u = sp.m_vec(R_sk, d)
            # torque-row coefficients: the motion subspaces (sensor frame) of the row's joints
            # whose subtree holds the slot
            s_rows = []
            for c_ in rows:
                terms = []
                b = slot.body
                while b >= 0 and em.region_of_body[b] == r:
                    body = tree.bodies[b]
                    if body.coord == c_:
                        Rj, pj = pose(b)
                        axis = (Rj[0][2], Rj[1][2], Rj[2][2])
                        S = ((sp.v_cross(pj, axis), axis) if body.kind == "revolute"
                             else (axis, sp.ZERO3))  # fmt: skip
                        terms.append(tuple(sp.v_scale(body.mult, x) for x in S))
                    b = body.parent
                s = ((sp.v_sum([t[0] for t in terms]), sp.v_sum([t[1] for t in terms]))
                     if terms else (sp.ZERO3, sp.ZERO3))  # fmt: skip
                s_rows.append([mul(x, tau_mask[c_]) for x in (*s[0], *s[1])])
            maps[k] = SlotMap(R_sk, c, u, d, s_rows, active[k])
            G6 = _gram6(slot.kind, c, u)
            # Y_k = [A_k; T_k] with T_k = s^T A_k: G += act [G6, G6 s; s^T G6, s^T G6 s]
            Gs = [[sum_([mul(G6[i][j], sv[j]) for j in range(6)]) for i in range(6)]
                  for sv in s_rows]  # fmt: skip
            blocks = {}
            for i in range(6):
                for j in range(i + 1):
                    blocks[i, j] = G6[i][j]
            for t, gs in enumerate(Gs):
                for j in range(6):
                    blocks[6 + t, j] = gs[j]
                for t2 in range(t + 1):
                    blocks[6 + t, 6 + t2] = sum_([mul(gs[j], s_rows[t2][j]) for j in range(6)])
            for (i, j), g in blocks.items():
                G[i][j] = add(G[i][j], mul(active[k], g))
        for i in range(R):
            for j in range(i):
                G[j][i] = G[i][j]
        grams.append(G)
    return maps, grams


def body_in_sensor(em: EstimationModel, X: list, r: int) -> Callable[[int], sp.Pose]:
    """Poses of region ``r``'s bodies in its sensor frame, computed along the paths to them.

    Args:
        em: the estimation model.
        X: joint placements (stage 1).
        r: the region.

    Returns:
        ``pose(body)`` -> ``T_sensor_body`` (the body's internal frame), memoised.
    """
    tree = em.tree
    T: dict[int, sp.Pose] = {em.regions[r].child: sp.pose_inverse(em.regions[r].T_child_sensor)}

    def pose(body: int) -> sp.Pose:
        if body not in T:
            T[body] = sp.pose_compose(pose(tree.bodies[body].parent), X[body])
        return T[body]

    return pose


def _unit(x: Sequence[Scalar]) -> sp.V3:
    n2 = sum_([mul(c, c) for c in x])
    inv = select(gt(n2, 0.0), div(1.0, sqrt(select(gt(n2, 0.0), n2, 1.0))), 0.0)
    return tuple(mul(c, inv) for c in x)


def contact_wrenches(
    em: EstimationModel,
    maps: list[SlotMap | None],
    ys: list[list[Scalar]],
    known: Sequence[Sequence[Scalar]] | None,
    active: Sequence[Scalar],
) -> list[sp.Force]:
    """Stage 5: ``w_k = P_k Y_k^T y`` per slot (link frame, moment about the contact point).

    Args:
        em: the estimation model.
        maps: stage 3's slot maps.
        ys: per region, the solve's ``y``.
        known: per slot, the given wrench (``known`` slots), or None.
        active: per slot, its 0/1 activity.
    """
    out: list[sp.Force] = []
    for k, slot in enumerate(em.slots):
        if slot.kind == "known":
            w = known[k] if known is not None else (0.0,) * 6
            out.append((tuple(mul(active[k], x) for x in w[:3]),
                        tuple(mul(active[k], x) for x in w[3:])))  # fmt: skip
        else:
            out.append(_slot_wrench(slot.kind, maps[k], ys[slot.region]))
    return out


def _slot_wrench(kind: str, m: SlotMap, y: Sequence[Scalar]) -> sp.Force:
    """``P_k Y_k^T y`` of one slot (link frame, moment about the contact point)."""
    # z = y_6 + sum_t y_t s_t (a wrench-like dual in the sensor frame)
    z = [sum_([y[i], *(mul(y[6 + t], s[i]) for t, s in enumerate(m.s))]) for i in range(6)]
    zf, zn = tuple(z[:3]), tuple(z[3:])
    g = sp.v_add(zf, sp.v_cross(zn, m.c))  # A^T z's force part, in the sensor frame
    if kind == "force_dir":
        mag = mul(m.active, sp.v_dot(m.u, g))
        return sp.v_scale(mag, m.d), sp.ZERO3
    force = tuple(mul(m.active, x) for x in sp.mT_vec(m.R, g))
    if kind == "wrench":
        return force, tuple(mul(m.active, x) for x in sp.mT_vec(m.R, zn))
    return force, sp.ZERO3


def backward(
    em: EstimationModel,
    X: list,
    tau: list[Scalar],
    pos: Sequence[Sequence[Scalar]],
    w: list[sp.Force],
) -> list[Scalar]:
    """Stage 6: joint torques with the estimated contacts.

    The contacts' share is one more backward pass over the bodies between each contact and its
    sensor (a contact's wrench stops at its sensor, whose reading already holds it):
    ``tau = tau_b - S^T (X^* w)``.

    Args:
        em: the estimation model.
        X: joint placements.
        tau: stage 2's torques without the unknown contacts.
        pos: per slot, the contact point (link frame).
        w: per slot, stage 5's estimated wrench (``known`` slots excluded: already in ``tau``).
    """
    tree = em.tree
    nb = len(tree.bodies)
    f: list = [(sp.ZERO3, sp.ZERO3)] * nb
    for k, slot in enumerate(em.slots):
        if slot.kind == "known":
            continue
        wb = wrench_on_body(slot, contact_point(slot, pos[k]), w[k])
        f[slot.body] = sp.add_forces([f[slot.body], wb])
    zero = (sp.ZERO3, sp.ZERO3)
    _, tau_c = _dyn.backward_pass(tree, X, f, {reg.child: zero for reg in em.regions})
    return [sub(t, tc) for t, tc in zip(tau, tau_c, strict=True)]


def covariance(
    em: EstimationModel,
    maps: list[SlotMap | None],
    factors: list[Factorization],
    sigma: Sequence[Sequence[Sequence[Scalar]]],
    chol: Sequence[Sequence[Sequence[Scalar]] | None] | None = None,
) -> list[list[Scalar]]:
    """Stage 7: ``cov(w_k) = M_k Sigma M_k^T``, ``M_k`` the solve's map from ``b`` to ``w_k``.

    First-order propagation of each region's row noise ``Sigma`` (``R x R``: its sensor's reading
    covariance, sensor frame, then the variances of its torque rows; nested sensors' noise is not
    included) through the solve: ``M_k = P_k Y_k^T pinv(G)`` unweighted, ``P_k Y_k^T L^-T
    pinv(G~) L^-1`` weighted (``chol``: the factor ``L`` of ``Sigma``), where ``cov(w_k)`` is
    ``P_k Y_k^T pinv(A~^T A~) Y_k P_k``, the weighted estimate's covariance. Per slot, 36 scalars
    (row-major ``[force; moment]``).
    """
    out = []
    for k, slot in enumerate(em.slots):
        if slot.kind == "known":
            out.append([0.0] * 36)
            continue
        r = slot.region
        f = factors[r]
        L = None if chol is None else chol[r]
        S = sigma[r]
        Rr = len(f.ok)
        rows = [j for j in range(Rr) if any(not (is_const(v) and v == 0) for v in S[j])]
        cols = []
        for j in rows:  # d w_k / d b_j, the solve being linear in b
            e = [1.0 if i == j else 0.0 for i in range(Rr)]
            if L is None:
                y = solve_factored(f, e)
            else:  # y = L^-T pinv(G~) L^-1 e
                y = triu_t_solve(L, solve_factored(f, tril_solve(L, e)))
            wk = _slot_wrench(slot.kind, maps[k], y)
            cols.append([*wk[0], *wk[1]])
        M = [[cols[a][i] for a in range(len(rows))] for i in range(6)]
        MS = [[sum_([mul(M[i][a], S[ra][rb]) for a, ra in enumerate(rows)]) for rb in rows]
              for i in range(6)]  # fmt: skip
        out.append([sum_([mul(MS[i][bb], M[j][bb]) for bb in range(len(rows))])
                    for i in range(6) for j in range(6)])  # fmt: skip
    return out


def contact_matrix(
    em: EstimationModel, maps: list[SlotMap | None], r: int
) -> tuple[list[list[Scalar]], list[tuple[int, int]]]:
    """The explicit ``A`` of region ``r`` (rows: 6 sensor rows, then the torque rows).

    Columns are the unknowns of the region's slots in slot order, in each slot's link frame:
    ``force`` (3), ``wrench`` (force 3, then moment about the point 3), ``force_dir`` (the
    magnitude, 1); a slot's columns are zero in frames where it is inactive. ``A A^T`` is
    stage 3's Gram matrix and ``A^T y`` stage 5's unknowns.

    Args:
        em: the estimation model.
        maps: stage 3's slot maps.
        r: the region.

    Returns:
        ``(A, columns)``: ``R`` rows of ``u`` scalars, and per column ``(slot, component)``.
    """
    cols: list[list[Scalar]] = []
    labels: list[tuple[int, int]] = []
    for k in em.regions[r].slots:
        slot, m = em.slots[k], maps[k]
        if slot.kind == "known":
            continue
        if slot.kind == "force_dir":
            dirs = [m.u]
        else:
            dirs = [(m.R[0][j], m.R[1][j], m.R[2][j]) for j in range(3)]
        six = [(*f, *sp.v_cross(m.c, f)) for f in dirs]
        if slot.kind == "wrench":
            six += [(0.0, 0.0, 0.0, *f) for f in dirs]
        for j, col in enumerate(six):
            full = [*col, *(sum_([mul(sv[i], col[i]) for i in range(6)]) for sv in m.s)]
            cols.append([mul(m.active, v) for v in full])
            labels.append((k, j))
    own = [maps[k] for k in em.regions[r].slots if maps[k] is not None]
    R = 6 + (len(own[0].s) if own else 0)
    return [[col[i] for col in cols] for i in range(R)], labels


def nullspace_basis(
    A: Sequence[Sequence[Scalar]],
    f: Factorization,
    present: Sequence[Scalar],
    rtol: float,
) -> list[list[Scalar]]:
    """An orthonormal basis of ``null(A)`` among the present unknowns (columns, zero-padded).

    ``P_N = D - A^T pinv(A A^T) A`` (``D``: 1 on the present unknowns) projects onto the null
    space; ``pinv(A A^T) A`` comes from the solve's factorization ``f`` (column by column), and a
    pivoted Cholesky of ``P_N`` with modified Gram-Schmidt (:func:`torchcontact.solve.factorize`)
    gives its orthonormal range. The basis vectors fill the first ``u - rank`` columns.

    Args:
        A: ``R`` rows of ``u`` scalars (:func:`contact_matrix`).
        f: the factorization of ``A A^T`` (stage 4).
        present: per unknown, 1 if its slot is active, else 0.
        rtol: rank tolerance of the pivoted Cholesky of ``P_N`` (eigenvalues 0 or 1).

    Returns:
        ``u`` columns of ``u`` scalars.
    """
    R, u = len(A), len(present)
    PR = []  # columns of A^T pinv(G) A
    for j in range(u):
        y = solve_factored(f, [A[i][j] for i in range(R)])
        PR.append([sum_([mul(A[i][c], y[i]) for i in range(R)]) for c in range(u)])
    PN = [[sub(present[i] if i == j else 0.0, PR[j][i]) for j in range(u)] for i in range(u)]
    fn = factorize(PN, rtol)
    return [[select(fn.ok[k], v, 0.0) for v in fn.q[k]] for k in range(u)]
