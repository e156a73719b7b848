"""Stage 2 of the single-frame graph: poses, motion and body wrenches of every body at once.

Root frame, about the root origin (Featherstone, *Rigid Body Dynamics Algorithms*, 2008, Ch. 2
and 5), the tree folded into constant matrices:

* **poses**: each joint transform ``T_parent_i = C_i Rz(q_i)`` is linear in ``(cos q_i, sin
  q_i)``; poses in the root frame are prefix products along the tree, by pointer doubling
  (``T_i <- T_{a_k(i)} T_i`` with ``a_k`` the ``2^k``-th ancestor): ``log2`` of the depth
  compositions of all bodies at once, each a batched product of 4 x 4 homogeneous matrices;
* **motion**: with motion subspaces ``S_i`` in the root frame, ``v_i = v_0 + sum_{j<=i} S_j
  qd_j`` and ``a_i = a_0 + sum_{j<=i} (S_j qdd_j + v_j x S_j qd_j)``: two products with the
  constant ancestor matrix;
* **body wrenches** ``I_i a_i + v_i x* I_i v_i`` in each body frame, moved to the root frame.

Each stage but the poses is a :func:`~torchcontact.onnx.builder.bilinear` trace of
:mod:`torchcontact.spatial` code (the poses' per-body maps are evaluated from it);
:mod:`torchcontact.estimation.stages` ``forward`` is the same function per body.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from torchcontact import spatial as sp
from torchcontact._scalar import mul
from torchcontact.onnx.builder import Operand, bilinear
from torchcontact.onnx.step.context import StepContext
from torchcontact.onnx.step.forms import (
    TP_ONE,
    const_force_map,
    flat,
    force_to_parent,
    motion_to_child,
    skew,
    split,
    tp,
)

__all__ = [
    "body_wrenches",
    "motion",
    "pose_features",
    "poses",
    "readings_root",
    "subspaces",
    "wrench_to_root",
]


def _joint_pose(ctx: StepContext, i: int, a: list) -> sp.Pose:
    """``T_parent_i`` of body ``i`` from ``[cos, sin, displacement, 1]`` (linear in them)."""
    b = ctx.em.tree.bodies[i]
    if i == 0:
        return sp.EYE3, sp.ZERO3
    c, s, d = a[0], a[1], a[2]
    if b.kind == "revolute":
        return sp.m_mul(b.C, sp.rot_z(c, s)), b.p
    if b.kind == "prismatic":
        axis = tuple(row[2] for row in b.C)
        return b.C, sp.v_add(b.p, sp.v_scale(d, axis))
    return b.C, b.p


def poses(ctx: StepContext, e: str, idx: dict, zero: int, ce: str | None = None) -> str:
    """``T_root_i`` of every body as homogeneous matrices, ``(nb, 16)`` rows (4 x 4 row-major).

    Each joint transform ``T_parent_i`` is affine in ``(cos, sin, displacement)`` of its joint:
    one ``Gather`` of those and one batched ``MatMul`` by per-body constant maps give all of
    them, ``(nb, 4, 4)``. The poses are prefix products along the tree by pointer doubling,
    ``T_i <- T_{a(i)} T_i`` with ``a(i)`` the ``2^k``-th ancestor (the root is its own parent,
    the identity): each step one ``Gather`` of the ancestors' rows and one batched ``MatMul``.

    Args:
        ctx: the graph.
        e: the affine entries, a ``(1, E)`` row.
        idx: their indices (:func:`~torchcontact.onnx.step.inputs.plan`).
        zero: the index of a constant 0 entry (``cos 0 = 1``).
        ce: ``Cos(e)`` when computed already (None: computed here).
    """
    gb, tree, nb = ctx.gb, ctx.em.tree, ctx.nb
    has_pri = any(b.kind == "prismatic" for b in tree.bodies)
    ce = gb.op("Cos", e) if ce is None else ce
    E = int(idx["n_entries"])
    src = gb.op("Concat", ce, e, axis=1) if has_pri else ce
    # (without prismatic joints the displacement column is any finite entry: its map is 0)
    disp = [E + idx["disp"][i] if has_pri else zero for i in range(nb)]
    index = np.array([[idx["cos"][i], idx["sin"][i], disp[i], zero] for i in range(nb)])
    # the joint transforms: [cos, sin, d, 1] (1, 4) times a (4, 16) map per body
    Cx = np.zeros((nb, 4, 16))
    for i in range(nb):
        base = _homogeneous(_joint_pose(ctx, i, [0.0, 0.0, 0.0]))
        Cx[i, 3] = base
        for j in range(3):
            Cx[i, j] = _homogeneous(_joint_pose(ctx, i, [float(j == k) for k in range(3)])) - base
    g = gb.op("Gather", src, gb.i(index[:, None, :]), axis=1)  # (1, nb, 1, 4)
    X = gb.op("Reshape", gb.op("MatMul", g, gb.f(Cx)), gb.i([nb, 4, 4]))
    # pointer doubling: T_parent(i) T_i first, then 2^k-th ancestors
    par = [max(b.parent, 0) for b in tree.bodies]
    T = gb.op("MatMul", gb.op("Gather", X, gb.i(par), axis=0), X)
    depth = max(ctx.depths())
    anc = [par[par[i]] for i in range(nb)]
    hop = 2
    while hop < depth:
        T = gb.op("MatMul", gb.op("Gather", T, gb.i(anc), axis=0), T)
        anc = [anc[anc[i]] for i in range(nb)]
        hop *= 2
    return gb.op("Reshape", T, gb.i([nb, 16]))


def _homogeneous(pose: sp.Pose) -> np.ndarray:
    """The 16 row-major entries of a pose's 4 x 4 homogeneous matrix (float constants)."""
    R, p = pose
    H = np.eye(4)
    H[:3, :3] = np.array([[float(v) for v in row] for row in R])
    H[:3, 3] = [float(v) for v in p]
    return H.reshape(16)


def pose_features(ctx: StepContext, T: str) -> str:
    """``[R, p, pR, -R^T p, 1]`` of every pose (:func:`poses`), ``(nb, 25)``."""

    def features(_i: int, t: list, _b: list) -> list:
        R, p = (tuple(t[0:3]), tuple(t[4:7]), tuple(t[8:11])), (t[3], t[7], t[11])
        return [*flat(R), *p, *flat(sp.m_mul(skew(p), R)), *sp.v_neg(sp.mT_vec(R, p))]

    return bilinear(ctx.gb, Operand(T, 16, one=15), None, ctx.nb, features, 24, hint="tp")


def subspace(ctx: StepContext, i: int, t: list) -> tuple:
    """Body ``i``'s motion subspace in the root frame, from its pose features.

    ``[p x z; z]`` for revolute bodies (and fixed ones, whose rates are 0), ``[z; 0]`` for
    prismatic ones, with ``z = R e_z`` and ``p x z = (pR) e_z``.
    """
    R, _, pR, _ = tp(t)
    z = tuple(R[r][2] for r in range(3))
    if ctx.em.tree.bodies[i].kind == "prismatic":
        return (*z, 0.0, 0.0, 0.0)
    return (*(pR[r][2] for r in range(3)), *z)


def subspaces(ctx: StepContext, TP: str) -> str:
    """Motion subspaces of every body, root frame, ``(nb, 6)``."""
    return bilinear(ctx.gb, Operand(TP, 25, one=TP_ONE), None, ctx.nb,
                    lambda i, t, _b: list(subspace(ctx, i, t)), 6, one=False,
                    hint="s0")  # fmt: skip


def motion(ctx: StepContext, TP: str, e: str, idx: dict, base: np.ndarray | None,
           S0: str | None = None) -> str:  # fmt: skip
    """``[v, a, 1]`` of every body, ``(nb, 13)``, root frame about the root origin.

    Args:
        ctx: the graph.
        TP: pose features.
        e: the affine entries.
        idx: their indices.
        base: ``(1, 13)`` constant ``[v0, a0, 1]`` of a fixed base, or None (``idx["base"]``).
        S0: the motion subspaces (:func:`subspaces`) when computed already: the joint rates'
            terms ``[S qd, S qdd]`` are then one product with the rates' entries.
    """
    gb, tree, nb = ctx.gb, ctx.em.tree, ctx.nb
    if S0 is not None:
        # [S qd; S qdd; 0] (the root's and fixed bodies' rates are the entry 0)
        idx13 = np.array([[idx["qd"][i]] * 6 + [idx["qdd"][i]] * 6 + [idx["zero"]]
                          for i in range(nb)])  # fmt: skip
        D = np.zeros((6, 13))
        D[:, :6] = D[:, 6:12] = np.eye(6)
        rates = gb.op("Gather", e, gb.i(idx13), axis=0)
        VA = gb.op("Mul", gb.op("MatMul", S0, gb.f(D)), rates)
    else:
        index = np.array([[idx["qd"][i], idx["qdd"][i], idx["one"]] for i in range(nb)])

        def joint_rates(i: int, t: list, rate: list) -> list:
            # [S qd; S qdd] (fixed bodies and the root have rates 0)
            Sv = subspace(ctx, i, t)
            return [mul(s, rate[0]) for s in Sv] + [mul(s, rate[1]) for s in Sv] + [0.0]

        VA = bilinear(gb, Operand(TP, 25, one=TP_ONE), Operand(e, 3, "vec", one=2, index=index),
                      nb, joint_rates, 13, one=False, hint="rates")  # fmt: skip
    anc = np.zeros((nb, nb))
    for i in range(nb):
        j = i
        while j >= 0:
            anc[i, j] = 1.0
            j = tree.bodies[j].parent
    v0a0 = (
        gb.f(base)
        if base is not None
        else gb.op("Reshape", gb.op("Gather", e, gb.i(idx["base"]), axis=0), gb.i([1, 13]))
    )
    ancVA = gb.op("Gemm", gb.f(anc), VA, v0a0)

    def bias(_i: int, v: list, vj: list) -> list:
        # v_j x (S_j qd_j): the acceleration the joint rate adds as the body turns
        c = sp.motion_cross_motion(split(v[0:6]), split(vj[0:6]))
        return [0.0] * 6 + [*c[0], *c[1]] + [0.0]

    cross = bilinear(gb, Operand(ancVA, 13, one=12), Operand(VA, 13), nb, bias, 13, one=False,
                     hint="bias")  # fmt: skip
    return gb.op("Gemm", gb.f(anc), cross, ancVA)


def body_wrenches(ctx: StepContext, TP: str, VA: str,
                  deltas: Sequence[dict] = ()) -> tuple[str, str, str | None]:  # fmt: skip
    """Body wrenches ``I_i a_i + v_i x* I_i v_i`` and the motion in each body frame.

    Args:
        ctx: the graph.
        TP: pose features.
        VA: ``[v, a, 1]`` root frame (:func:`motion`).
        deltas: inertial changes (per correction stack, pruned body index -> ``(m, h,
            I_origin)``, internal frame): their Newton-Euler wrenches are computed in the same
            two stages, as more columns (the same monomials of the motion).

    Returns:
        ``(f0, VAb, F)``: the wrenches in the root frame ``(nb, 6)``, ``[v, a, 1]`` in each
        body frame ``(nb, 13)`` (what the inertial corrections apply their inertias to), and
        with ``deltas`` ``F = [f0, f_delta_1, ...]`` ``(nb, 6 (1 + len(deltas)))`` (root frame;
        0 on bodies a change does not touch), else None.
    """
    gb, tree, nb = ctx.gb, ctx.em.tree, ctx.nb

    def to_body(_i: int, t: list, va: list) -> list:
        R, _, pR, _ = tp(t)
        v = motion_to_child(R, pR, split(va[0:6]))
        a = motion_to_child(R, pR, split(va[6:12]))
        return [*v[0], *v[1], *a[0], *a[1]]

    VAb = bilinear(gb, Operand(TP, 25, one=TP_ONE), Operand(VA, 13, one=12), nb, to_body, 12,
                   hint="vab")  # fmt: skip

    def newton_euler(i: int, va: list, _b: list) -> list:
        b = tree.bodies[i]
        v, a = split(va[0:6]), split(va[6:12])
        Ia = sp.inertia_apply(b.mass, b.com, b.inertia, a)
        vxIv = sp.motion_cross_force(v, sp.inertia_apply(b.mass, b.com, b.inertia, v))
        out = [*sp.v_add(Ia[0], vxIv[0]), *sp.v_add(Ia[1], vxIv[1])]
        for delta in deltas:  # the inertial changes' wrenches (sp.body_wrench_params)
            if i not in delta:
                out += [0.0] * 6
                continue
            m, h, Io = delta[i]
            f = sp.body_wrench_params(m, sp.const_vec(h), sp.const_mat(Io), v, a)
            out += [*f[0], *f[1]]
        return out

    n = 6 * (1 + len(deltas))
    fb = bilinear(gb, Operand(VAb, 13, one=12), None, nb, newton_euler, n, hint="fb")
    if not deltas:
        return bodies_to_root(ctx, TP, fb, "f0", 1), VAb, None
    # f0 and F as two products of the stage's terms (no Slice of F)
    F, f0 = bodies_to_root(ctx, TP, fb, "f0", 1 + len(deltas), parts=[(0, n), (0, 6)])
    return f0, VAb, F


def bodies_to_root(ctx: StepContext, TP: str, fb: str, hint: str, m: int = 1,
                   parts: Sequence[tuple[int, int]] | None = None) -> str | list[str]:  # fmt: skip
    """Per-body wrenches in their body frames, in the root frame.

    Args:
        ctx: the graph.
        TP: pose features.
        fb: ``(nb, 6 m + 1)``: ``m`` wrenches per body, body frame, a 1 column last.
        hint: the value names' hint.
        m: wrenches per body.
        parts: column ranges of the result to return instead, each its own product
            (:func:`~torchcontact.onnx.builder.bilinear`).

    Returns:
        ``(nb, 6 m)`` root frame (with ``parts``, a list of its column ranges).
    """

    def to_root(_i: int, t: list, f: list) -> list:
        R, _, pR, _ = tp(t)
        out = []
        for j in range(m):
            w = force_to_parent(R, pR, split(f[6 * j : 6 * j + 6]))
            out += [*w[0], *w[1]]
        return out

    return bilinear(ctx.gb, Operand(TP, 25, one=TP_ONE), Operand(fb, 6 * m + 1, one=6 * m),
                    ctx.nb, to_root, 6 * m, one=False, hint=hint, parts=parts)  # fmt: skip


def wrench_to_root(ctx: StepContext, child: int, t: list | None, w: sp.Force) -> sp.Force:
    """A wrench in body ``child``'s frame, in the root frame (a constant pose when static)."""
    static = ctx.static_pose(child)
    if static is not None:
        return sp.force_to_parent((sp.const_mat(static[0]), sp.const_vec(static[1])), w)
    R, _, pR, _ = tp(t)
    return force_to_parent(R, pR, w)


def readings_root(ctx: StepContext, TP: str, e: str, idx: dict,
                  corrections: Sequence[tuple[int, str]] = ()) -> str:  # fmt: skip
    """Each sensor's wrench on its region, root frame about the root origin, ``(S, 6)``.

    Args:
        ctx: the graph.
        TP: pose features.
        e: the affine entries.
        idx: their indices.
        corrections: ``(region, c)`` with ``c`` ``(1, 6)`` a correction to subtract from that
            sensor's reading (sensor frame, measure direction: :mod:`.corrections`); it is taken
            from the reading in the child body's frame, before the one move to the root frame.
    """
    gb, S = ctx.gb, ctx.S
    regs = ctx.em.regions
    childs = [reg.child for reg in regs]

    def to_root(r: int, t: list, w: list) -> list:
        out = wrench_to_root(ctx, childs[r], t, split(w[0:6]))
        return [*out[0], *out[1]]

    pose = Operand(TP, 25, "nd", one=TP_ONE, row_of=childs)
    if not corrections:
        return bilinear(gb, pose, Operand(e, 7, "vec", one=6, index=np.array(idx["W_c"])), S,
                        to_root, 6, one=False, hint="w0")  # fmt: skip
    W = gb.op("Gather", e, gb.i(np.array(idx["W_c"])), axis=0)  # (S, 7) child frame, 1 last
    for r, c in corrections:
        # sign Ad(T_child_sensor) c, as the row c A (the reading's own map, inputs.plan)
        Ad = const_force_map(lambda f, T=regs[r].T_child_sensor: sp.force_to_parent(T, f))
        A = np.zeros((6, 7))
        A[:, :6] = regs[r].sign * Ad.T
        if S == 1:
            W = gb.op("Gemm", c, gb.f(A), W, alpha=-1.0)
        else:
            col = np.zeros((S, 1))
            col[r, 0] = 1.0
            W = gb.op("Gemm", gb.f(col), gb.op("MatMul", c, gb.f(A)), W, alpha=-1.0)
    return bilinear(gb, pose, Operand(W, 7, one=6), S, to_root, 6, one=False, hint="w0")
