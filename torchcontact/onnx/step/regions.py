"""Stage 3 of the single-frame graph: slot geometry, known contacts, ``b`` and the Gram matrices.

Del Prete et al., HRI 2012, Sec. 2: per region (sensor), its right side ``b`` (the transmitted
wrench at the sensor minus its reading, sensor frame; then one row per measured joint torque),
each slot's contact point and frame in the sensor frame, its Gram block ``A_k P_k A_k^T``
(``stages._gram6``, the estimator's own) and
``G = sum_k act_k Y_k P_k Y_k^T`` with ``Y_k = [I; s_k^T] A_k`` for torque rows. The transmitted
wrenches are ``F = D (f - contacts) + D_parent(sensor) W``: one product with the constant
"subtree cut at the sensors" matrix ``D`` (:meth:`EstimationModel.cut_matrix`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchcontact import spatial as sp
from torchcontact._scalar import mul, sum_
from torchcontact.estimation import stages
from torchcontact.onnx.builder import Operand, bilinear
from torchcontact.onnx.step.context import StepContext
from torchcontact.onnx.step.forms import (
    TP_ONE,
    flat,
    force_to_child,
    motion_to_child,
    rows,
    split,
    tp,
)
from torchcontact.onnx.step.kinematics import wrench_to_root

__all__ = [
    "Grams",
    "grams",
    "known_wrenches",
    "region_b",
    "slot_geometry",
    "slots_to_root",
    "torque_row_coefs",
    "transmitted",
]


def transmitted(ctx: StepContext, f0: str, W0: str) -> str:
    """``F = D f + D_parent(sensor) W``: per-body transmitted wrenches, root frame, ``(nb, 6)``."""
    gb, D = ctx.gb, ctx.cut
    E = D[:, [ctx.em.tree.bodies[reg.child].parent for reg in ctx.em.regions]]
    return gb.op("Gemm", gb.f(E), W0, gb.op("MatMul", gb.f(D), f0))


def slot_geometry(ctx: StepContext, TP: str, e: str, idx: dict) -> str:
    """Per slot ``[c (3), R (9), 1]``: contact point and slot-body rotation, sensor frame.

    ``R`` is the rotation of the slot body's internal frame in the sensor frame (the slot's own
    constant rotation is applied where the link frame is needed).
    """
    gb, em = ctx.gb, ctx.em
    if not em.slots:
        return gb.f(np.zeros((0, 13)))
    regs = em.regions
    slot_child = [regs[s.region].child for s in em.slots]
    slot_body = [s.body for s in em.slots]
    points = Operand(e, 4, "vec", one=3, index=np.array(idx["pos_b"]))
    if ctx.all_static(slot_child):
        # the sensors do not move: T_sensor_body = const * T_root_body
        def geom(k: int, t: list, pos: list) -> list:
            Rc, pc = ctx.static_pose(slot_child[k])
            T_sc = sp.pose_inverse(regs[em.slots[k].region].T_child_sensor)
            T_cr = sp.pose_inverse((sp.const_mat(Rc), sp.const_vec(pc)))
            Rs, ps = sp.pose_compose(sp.pose_compose(T_sc, T_cr), (rows(t[0:9]), tuple(t[9:12])))
            return [*sp.pose_apply((Rs, ps), tuple(pos[0:3])), *flat(Rs)]

        return bilinear(gb, Operand(TP, 25, "nd", one=TP_ONE, row_of=slot_body), points, ctx.K,
                        geom, 12, hint="slots")  # fmt: skip

    # T_sensor_body = T_cs^-1 T_child^-1 T_body, then the contact point
    def rel(k: int, tc: list, tb: list) -> list:
        Rc, _, _, pinv = tp(tc)
        T_sc = sp.pose_inverse(regs[em.slots[k].region].T_child_sensor)
        T_cb = sp.pose_compose((sp.m_T(Rc), pinv), (rows(tb[0:9]), tuple(tb[9:12])))
        R, p = sp.pose_compose(T_sc, T_cb)
        return [*flat(R), *p]

    Trel = bilinear(gb, Operand(TP, 25, "nd", one=TP_ONE, row_of=slot_child),
                    Operand(TP, 25, "nd", one=TP_ONE, row_of=slot_body), ctx.K, rel, 12,
                    hint="trel")  # fmt: skip

    def geom2(_k: int, t: list, pos: list) -> list:
        R, p = rows(t[0:9]), tuple(t[9:12])
        return [*sp.pose_apply((R, p), tuple(pos[0:3])), *flat(R)]

    return bilinear(gb, Operand(Trel, 13, one=12), points, ctx.K, geom2, 12, hint="slots")


def known_wrenches(ctx: StepContext, Cg: str, e: str, idx: dict, actK: str) -> str:
    """Known slots' wrenches in their sensor frame about its origin, ``(K, 6)``."""
    em = ctx.em
    index = np.array([list(w) + [idx["one"]] for w in idx["wrench"]])

    def rotate(k: int, g: list, w: list) -> list:
        if em.slots[k].kind != "known":
            return [0.0] * 6
        Rs = sp.m_mul(rows(g[3:12]), em.slots[k].R)  # link frame in the sensor frame
        return [*sp.m_vec(Rs, tuple(w[0:3])), *sp.m_vec(Rs, tuple(w[3:6]))]

    fn = bilinear(ctx.gb, Operand(Cg, 13, one=12), Operand(e, 7, "vec", one=6, index=index),
                  ctx.K, rotate, 6, hint="known")  # fmt: skip

    def shift(_k: int, g: list, w: list) -> list:
        # moment about the sensor origin: n + c x f
        f = tuple(w[0:3])
        return [*f, *sp.v_add(tuple(w[3:6]), sp.v_cross(tuple(g[0:3]), f))]

    w = bilinear(ctx.gb, Operand(Cg, 13, one=12), Operand(fn, 7, one=6), ctx.K, shift, 6,
                 one=False, hint="known")  # fmt: skip
    return ctx.gb.op("Mul", w, actK)


def slots_to_root(ctx: StepContext, TP: str, ws: str, first: int = 0) -> str:
    """Per-slot wrenches given in their sensor frame, in the root frame, ``(K, 6)``.

    Args:
        ctx: the graph.
        TP: pose features.
        ws: ``(K, first + 6)``, each slot's wrench in columns ``first .. first + 5`` (the
            stage's column selection picks them: no ``Slice`` of its own).
        first: the first column of the wrenches.
    """
    em = ctx.em
    childs = [em.regions[s.region].child for s in em.slots]
    n = first + 6

    def to_root(k: int, t: list | None, w: list) -> list:
        reg = em.regions[em.slots[k].region]
        f = sp.force_to_parent(reg.T_child_sensor, split(w[first:n]))
        o = wrench_to_root(ctx, reg.child, t, f)
        return [*o[0], *o[1]]

    if ctx.all_static(childs):
        return bilinear(ctx.gb, Operand(ws, n), None, ctx.K, lambda k, w, _b: to_root(k, None, w),
                        6, one=False, hint="om0")  # fmt: skip
    return bilinear(ctx.gb, Operand(TP, 25, "nd", one=TP_ONE, row_of=childs), Operand(ws, n),
                    ctx.K, to_root, 6, one=False, hint="om0")  # fmt: skip


def region_b(ctx, TP, Fb, S0, e, idx, ws_corr: str | None, ws_terms=()) -> list[str]:
    """Per region, its right side ``b`` as an ``(R, 1)`` column (sensor rows, torque rows).

    Args:
        ctx: the graph.
        TP: pose features.
        Fb: transmitted wrenches, root frame.
        S0: motion subspaces, root frame.
        e: the affine entries.
        idx: their indices.
        ws_corr: ``(S, 6)`` corrections subtracted from the readings (sensor frame, signed), or
            None.
        ws_terms: more of them, ``[(col (S, 1), c (1, 6))]`` for ``col c`` each (the native
            stacks', :func:`~torchcontact.onnx.step.corrections.native_corrections`): one
            ``Gemm`` each.
    """
    gb, regs = ctx.gb, ctx.em.regions
    childs = [reg.child for reg in regs]

    def to_sensor(r: int, t: list | None, F: list) -> list:
        Fs = sp.force_to_child(regs[r].T_child_sensor, root_to_child(ctx, regs[r].child, t, F))
        return [*Fs[0], *Fs[1]]

    # one region whose child moves, no online corrections: b comes out of the stage as the
    # (6, 1) column the solve takes (its product transposed), else as (S, 6) rows
    column = ctx.S == 1 and ws_corr is None and not ctx.all_static(childs)
    # the readings (less their corrections) enter as the last product's Gemm bias: b = F_s - W_s
    W_idx = np.array(idx["W_s"])
    Ws = gb.op("Gather", e, gb.i(W_idx.T if column else W_idx), axis=0)  # (6, 1) or (S, 6)
    for col, c in ws_terms:  # natively built corrections: W_s - col c
        Ws = (
            gb.op("Gemm", c, gb.f(-col), Ws, transA=1)
            if column
            else gb.op("Gemm", gb.f(-col), c, Ws)
        )
    if ws_corr is not None:
        Ws = gb.op("Sub", Ws, ws_corr)
    F_nd = Operand(Fb, 6, "nd", row_of=childs)
    if ctx.all_static(childs):
        b6 = bilinear(gb, F_nd, None, ctx.S, lambda r, F, _b: to_sensor(r, None, F), 6,
                      one=False, hint="fs", add=Ws, beta=-1.0)  # fmt: skip
    else:
        b6 = bilinear(gb, Operand(TP, 25, "nd", one=TP_ONE, row_of=childs), F_nd, ctx.S,
                      to_sensor, 6, one=False, hint="fs", add=Ws, beta=-1.0,
                      transpose=column)  # fmt: skip
    # per region its (6, 1) column: b6 itself, one Reshape for one region, else rows of b6^T
    b6T = None if ctx.S == 1 else gb.op("Transpose", b6, perm=[1, 0])
    out = []
    for r, reg in enumerate(regs):
        if column:
            b = b6
        elif b6T is None:
            b = gb.op("Reshape", b6, gb.i([6, 1]))
        else:
            b = gb.op("Gather", b6T, gb.i([r]), axis=1)
        if ctx.flags.torque_rows and reg.torque_coords:
            b = gb.op("Concat", b, _torque_b(ctx, r, S0, Fb, e, idx), axis=0)
        out.append(b)
    return out


def root_to_child(ctx: StepContext, child: int, t: list | None, v: list, motion: bool = False):
    """A root-frame wrench (or twist, ``motion``) in body ``child``'s frame.

    The body's pose is a constant when no joint moves it (:meth:`StepContext.static_pose`),
    else its pose feature row ``t``.
    """
    static = ctx.static_pose(child)
    if static is not None:
        T = (sp.const_mat(static[0]), sp.const_vec(static[1]))
        return (sp.motion_to_child if motion else sp.force_to_child)(T, split(v))
    R, _, pR, _ = tp(t)
    return (motion_to_child if motion else force_to_child)(R, pR, split(v))


def _coord_matrix(ctx: StepContext, coords) -> np.ndarray:
    """``M[t, i] = mult_i`` where body ``i``'s joint drives coordinate ``coords[t]``."""
    M = np.zeros((len(coords), ctx.nb))
    for t, c in enumerate(coords):
        for i, b in enumerate(ctx.em.tree.bodies):
            if b.coord == c:
                M[t, i] = b.mult
    return M


def _torque_b(ctx: StepContext, r: int, S0: str, Fb: str, e: str, idx: dict) -> str:
    """Torque rows of region ``r``'s ``b``: ``(sum mult S . F - tau_meas) * mask``."""
    gb = ctx.gb
    coords = ctx.em.regions[r].torque_coords
    SF = gb.op("ReduceSum", gb.op("Mul", S0, Fb), gb.i([1]), keepdims=1)  # (nb, 1)
    tm = gb.op("Gather", e, gb.i([[idx["tau_meas"][c]] for c in coords]), axis=0)
    mk = gb.op("Gather", e, gb.i([[idx["tau_mask"][c]] for c in coords]), axis=0)
    mk = gb.cast(gb.op("Greater", mk, gb.f(0.5)))
    return gb.op("Mul", gb.op("Gemm", gb.f(_coord_matrix(ctx, coords)), SF, tm, beta=-1.0), mk)


def torque_row_coefs(ctx, TP, S0, e, idx) -> tuple[str, list[tuple[int, int, int]]]:
    """``s_kt``: per (slot, torque row) the summed motion subspaces, sensor frame, masked.

    Returns:
        ``(sum_k T_k, 6)`` rows ordered slot-major over the torque rows of the slot's region,
        and per row its ``(slot, row, coordinate)``.
    """
    gb, em, tree = ctx.gb, ctx.em, ctx.em.tree
    pairs = [(k, t, c) for k, slot in enumerate(em.slots)
             for t, c in enumerate(em.regions[slot.region].torque_coords)]  # fmt: skip
    if not pairs:
        return gb.f(np.zeros((0, 6))), pairs
    # sum over the joints of coordinate c on the path slot body -> region child
    Mp = np.zeros((len(pairs), ctx.nb))
    for n, (k, _t, c) in enumerate(pairs):
        slot = em.slots[k]
        b = slot.body
        while b >= 0 and em.region_of_body[b] == slot.region:
            if tree.bodies[b].coord == c:
                Mp[n, b] += tree.bodies[b].mult
            b = tree.bodies[b].parent
    S_sum = gb.op("Concat", gb.op("MatMul", gb.f(Mp), S0), gb.f(np.ones((len(pairs), 1))), axis=1)
    childs = [em.regions[em.slots[k].region].child for k, _, _ in pairs]

    def to_sensor(n: int, t: list, s: list) -> list:
        reg = em.regions[em.slots[pairs[n][0]].region]
        vc = root_to_child(ctx, reg.child, t, s, motion=True)
        vs = sp.motion_to_child(reg.T_child_sensor, vc)
        return [*vs[0], *vs[1]]

    s = bilinear(gb, Operand(TP, 25, "nd", one=TP_ONE, row_of=childs), Operand(S_sum, 7, one=6),
                 len(pairs), to_sensor, 6, one=False, hint="srow")  # fmt: skip
    mk = gb.op("Gather", e, gb.i([[idx["tau_mask"][c]] for _, _, c in pairs]), axis=0)
    return gb.op("Mul", s, gb.cast(gb.op("Greater", mk, gb.f(0.5)))), pairs


@dataclass(frozen=True)
class Grams:
    """What the Gram stage leaves for the solve and the outputs.

    Attributes:
        G: per region its ``(R, R)`` Gram matrix.
        geo: per slot ``[c, R, (u, d, c x u,) 1]`` in the sensor frame (``u`` the unit force
            direction of ``force_dir`` slots, ``d`` the same in the link frame).
        n_geo: columns of ``geo``.
    """

    G: list[str]
    geo: str
    n_geo: int


def grams(ctx, Cg, e, idx, actK, s_rows, pairs) -> Grams:
    """Per region its Gram matrix ``G = sum_k act_k Y_k P_k Y_k^T``, ``(R, R)``."""
    gb, em, kinds = ctx.gb, ctx.em, ctx.kinds
    geo, n_geo = Cg, 13
    if "force_dir" in kinds:
        K = ctx.K
        index = np.array([[3 * k, 3 * k + 1, 3 * k + 2, 3 * K] for k in range(K)])

        def direction(k: int, g: list, d: list) -> list:
            dk = tuple(d[0:3]) if kinds[k] == "force_dir" else sp.ZERO3
            return [*g[0:12], *sp.m_vec(sp.m_mul(rows(g[3:12]), em.slots[k].R), dk), *dk]

        geo = bilinear(gb, Operand(Cg, 13, one=12), Operand(_unit_dirs(ctx, e, idx), 4, "vec",
                       one=3, index=index), K, direction, 18, hint="u")  # fmt: skip
        geo = bilinear(gb, Operand(geo, 19, one=18), None, K,
                       lambda _k, g, _b: [*g[0:18], *sp.v_cross(tuple(g[0:3]), tuple(g[12:15]))],
                       21, hint="cu")  # fmt: skip
        n_geo = 22
    if not em.slots:
        return Grams([gb.f(np.zeros((6, 6))) for _ in em.regions], geo, n_geo)

    def gram6(k: int, g: list, _b: list) -> list:
        kind = kinds[k]
        if kind == "known":
            return [0.0] * 36
        if kind == "force_dir":  # the column [u; c x u] of A, squared (c x u precomputed)
            col = [*g[12:15], *g[18:21]]
            return [mul(col[i], col[j]) for i in range(6) for j in range(6)]
        return [x for row in stages._gram6(kind, tuple(g[0:3]), None) for x in row]

    G6 = bilinear(gb, Operand(geo, n_geo, one=n_geo - 1), None, ctx.K, gram6, 36, one=False,
                  hint="g6")  # fmt: skip
    out = []
    for r, reg in enumerate(em.regions):
        memb = np.zeros((ctx.K, 1))
        memb[list(reg.slots), 0] = 1.0
        a = actK if len(reg.slots) == ctx.K else gb.op("Mul", actK, gb.f(memb))
        G = gb.op("Reshape", gb.op("Gemm", a, G6, transA=1), gb.i([6, 6]))
        if ctx.flags.torque_rows and reg.torque_coords:
            G = _gram_torque_rows(ctx, r, G, G6, a, s_rows, pairs)
        out.append(G)
    return Grams(out, geo, n_geo)


def _unit_dirs(ctx: StepContext, e: str, idx: dict) -> str:
    """Slot directions normalised (zero stays zero), flat ``(3K + 1,)`` ending with a 1."""
    gb = ctx.gb
    d = gb.op("Gather", e, gb.i(np.array(idx["dir"])), axis=0)
    n2 = gb.op("ReduceSumSquare", d, gb.i([1]), keepdims=1)
    pos = gb.op("Greater", n2, gb.f(0.0))
    inv = gb.op("Where", pos, gb.op("Pow", gb.op("Where", pos, n2, gb.f(1.0)), gb.f(-0.5)),
                gb.f(0.0))  # fmt: skip
    u = gb.op("Reshape", gb.op("Mul", d, inv), gb.i([3 * ctx.K]))
    return gb.op("Concat", u, gb.f([1.0]), axis=0)


def _gram_torque_rows(ctx, r: int, G6sum: str, G6: str, a: str, s_rows: str, pairs) -> str:
    """Region ``r``'s Gram matrix with its torque rows: ``Y_k = [I; s_k^T] A_k``."""
    gb, em = ctx.gb, ctx.em
    R = 6 + len(em.regions[r].torque_coords)
    mine = [n for n, (k, _, _) in enumerate(pairs) if em.slots[k].region == r]
    slot_of = [pairs[n][0] for n in mine]
    # Gs[n] = G6_k s_n (6), then s_n'^T G6_k s_n for the pairs of one slot
    Gs = bilinear(gb, Operand(G6, 36, "nd", row_of=slot_of), Operand(s_rows, 6, "nd", row_of=mine),
                  len(mine),
                  lambda _n, g, s: [sum_([mul(g[6 * i + j], s[j]) for j in range(6)])
                                    for i in range(6)], 6, one=False, hint="gs")  # fmt: skip
    trip = [(n1, n2) for i1, n1 in enumerate(mine) for n2 in mine[: i1 + 1]
            if pairs[n1][0] == pairs[n2][0]]  # fmt: skip
    pos = {n: i for i, n in enumerate(mine)}
    sGs = bilinear(gb, Operand(Gs, 6, "nd", row_of=[pos[n1] for n1, _ in trip]),
                   Operand(s_rows, 6, "nd", row_of=[n2 for _, n2 in trip]), len(trip),
                   lambda _n, g, s: [sum_([mul(g[j], s[j]) for j in range(6)])], 1, one=False,
                   hint="sgs")  # fmt: skip
    # scatter into the (R, R) matrix, weighted by activity
    Pa = np.zeros((len(mine), ctx.K))
    for i, n in enumerate(mine):
        Pa[i, pairs[n][0]] = 1.0
    Pt = np.zeros((len(trip), ctx.K))
    for i, (n1, _) in enumerate(trip):
        Pt[i, pairs[n1][0]] = 1.0
    Gs_w = gb.op("Mul", Gs, gb.op("MatMul", gb.f(Pa), a))
    sGs_w = gb.op("Mul", sGs, gb.op("MatMul", gb.f(Pt), a))
    # block [6+t, j] = sum over slots of Gs rows with torque row t
    Lt = np.zeros((R * R, len(mine) * 6))
    for i, n in enumerate(mine):
        t = pairs[n][1]
        for j in range(6):
            Lt[(6 + t) * R + j, i * 6 + j] = 1.0
            Lt[j * R + 6 + t, i * 6 + j] = 1.0
    Ltt = np.zeros((R * R, len(trip)))
    for i, (n1, n2) in enumerate(trip):
        t1, t2 = pairs[n1][1], pairs[n2][1]
        Ltt[(6 + t1) * R + 6 + t2, i] = 1.0
        Ltt[(6 + t2) * R + 6 + t1, i] = 1.0
    P6 = np.zeros((R * R, 36))
    for i in range(6):
        for j in range(6):
            P6[i * R + j, i * 6 + j] = 1.0
    flatG = gb.op("Add", gb.op("MatMul", gb.f(Lt), gb.op("Reshape", Gs_w, gb.i([-1, 1]))),
                  gb.op("MatMul", gb.f(Ltt), sGs_w))  # fmt: skip
    flatG = gb.op("Gemm", gb.f(P6), gb.op("Reshape", G6sum, gb.i([36, 1])), flatG)
    return gb.op("Reshape", flatG, gb.i([R, R]))
