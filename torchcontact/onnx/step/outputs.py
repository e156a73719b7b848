"""Stage 5 of the single-frame graph: contact wrenches, joint torques and the packed output.

``w_k = P_k Y_k^T y`` per slot (link frame, about the point; Del Prete et al. Sec. 2.2), joint
torques ``tau_c = sum mult_i S_i . F_i`` with the estimated contacts (Sec. 2.3), rank, unknowns,
residual ``|b - G y|``, the covariance ``M_k Sigma M_k^T`` and the status; NaN where the status
is not 0, as :func:`torchcontact.estimation.programs.estimate_program` returns them.
"""

from __future__ import annotations

import numpy as np

from torchcontact import spatial as sp
from torchcontact._scalar import mul
from torchcontact.contacts import KINDS
from torchcontact.onnx.builder import Operand, bilinear
from torchcontact.onnx.format import StepLayout, state_out
from torchcontact.onnx.step.context import StepContext
from torchcontact.onnx.step.forms import rows
from torchcontact.onnx.step.regions import Grams
from torchcontact.status import Status

__all__ = ["contact_wrenches", "pack", "torques"]


def _region_vector(ctx: StepContext, ys: list, ncols: int) -> tuple[str, list[int], int]:
    """Every region's ``y`` (all columns) in one flat vector ending with a 1: ``(Y, base, one)``."""
    gb = ctx.gb
    parts, base = [], []
    offset = 0
    for r, reg in enumerate(ctx.em.regions):
        R = 6 + (len(reg.torque_coords) if ctx.flags.torque_rows else 0)
        base.append(offset)
        if ys[r] is None:
            parts.append(gb.f(np.zeros(R * ncols)))
        else:
            parts.append(gb.op("Reshape", ys[r], gb.i([R * ncols])))
        offset += R * ncols
    parts.append(gb.f([1.0]))
    return gb.op("Concat", *parts, axis=0), base, offset


def _duals(ctx, Y, base, one, ncols, s_rows, pairs) -> Operand:
    """``z = y[:6] + sum_t y[6 + t] s_kt`` per (column, slot), as an operand ``[z, 1]``."""
    gb, em, K = ctx.gb, ctx.em, ctx.K
    rws = [(j, k) for j in range(ncols) for k in range(K)]
    if not (ctx.flags.torque_rows and any(reg.torque_coords for reg in em.regions)):
        index = np.array([[base[em.slots[k].region] + i * ncols + j for i in range(6)] + [one]
                          for j, k in rws])  # fmt: skip
        return Operand(Y, 7, "vec", one=6, index=index)
    Tmax = max(len(reg.torque_coords) for reg in em.regions)
    yidx, srow = [], []
    for j, k in rws:
        ks = [n for n, (kk, _, _) in enumerate(pairs) if kk == k]
        yt = [base[em.slots[k].region] + (6 + t) * ncols + j for t in range(len(ks))]
        yidx.append(yt + [one] * (Tmax - len(ks)))
        srow.append(ks)
    # per (row, t): y_t * s_kt summed over t, plus y[:6]
    flat_pairs = [(ri, t) for ri in range(len(rws)) for t in range(Tmax)]
    s_of = [srow[ri][t] if t < len(srow[ri]) else 0 for ri, t in flat_pairs]
    valid = np.array([1.0 if t < len(srow[ri]) else 0.0 for ri, t in flat_pairs])
    yv = Operand(Y, 1, "vec", index=np.array([[yidx[ri][t]] for ri, t in flat_pairs]))
    zt = bilinear(gb, yv, Operand(s_rows, 6, "nd", row_of=s_of), len(flat_pairs),
                  lambda n, yy, s: [mul(valid[n], mul(yy[0], s[i])) for i in range(6)], 6,
                  one=False, hint="zt")  # fmt: skip
    Msum = np.zeros((len(rws), len(flat_pairs)))
    for n, (ri, _t) in enumerate(flat_pairs):
        Msum[ri, n] = 1.0
    where = [[base[em.slots[k].region] + i * ncols + j for i in range(6)] for j, k in rws]
    z = gb.op("Gemm", gb.f(Msum), zt, gb.op("Gather", Y, gb.i(where), axis=0))
    return Operand(gb.op("Concat", z, gb.f(np.ones((len(rws), 1))), axis=1), 7, one=6)


def contact_wrenches(ctx, gr: Grams, ys, s_rows, pairs, e, idx, actK, known: bool) -> str:
    """Per slot ``[force, moment, wrench in the sensor frame]``, ``(K * ncols, 12)``.

    Rows ``0..K-1`` hold the estimate (link frame, moment about the point; known slots their
    given wrench); with the covariance, rows ``j K .. (j + 1) K - 1`` the derivative with
    respect to ``b_j``. Inactive slots are zero.
    """
    gb, em, K, kinds = ctx.gb, ctx.em, ctx.K, ctx.kinds
    if K == 0:
        return gb.f(np.zeros((0, 12)))
    ncols = 7 if ctx.flags.covariance else 1
    if ncols == 1 and len(ys) == 1 and ys[0] is not None and s_rows is None:
        # one region, no torque rows: z = y, the solve's (6, 1) column, read as it is (no
        # Reshape, no Concat of a 1, no Gather)
        zsrc = Operand(ys[0], 6, "col")
    else:
        Y, base, one = _region_vector(ctx, ys, ncols)
        zsrc = _duals(ctx, Y, base, one, ncols, s_rows, pairs)
    rws = [(j, k) for j in range(ncols) for k in range(K)]
    slot_of = [k for _, k in rws]
    geo = Operand(gr.geo, gr.n_geo, "nd", one=gr.n_geo - 1, row_of=slot_of)

    def dual(_n: int, g: list, zz: list) -> list:
        # g = z_f + z_n x c: the force part of A^T z (sensor frame); z_n for wrenches
        zf, zn = tuple(zz[0:3]), tuple(zz[3:6])
        return [*sp.v_add(zf, sp.v_cross(zn, tuple(g[0:3]))), *zn]

    gz = bilinear(gb, geo, zsrc, len(rws), dual, 6, hint="gz")  # (rows, 7): [g, zn, 1]

    def out(n: int, g: list, w: list) -> list:
        # P_k Y_k^T y in the link frame, and A_k x_k (sensor frame)
        k = slot_of[n]
        kind = kinds[k]
        c, gf, zn = tuple(g[0:3]), tuple(w[0:3]), tuple(w[3:6])
        if kind == "known":
            return [0.0] * 12
        if kind == "force_dir":  # the magnitude along u; scaled in the next stage
            return [sp.v_dot(tuple(g[12:15]), gf)] + [0.0] * 11
        Rs = sp.m_mul(rows(g[3:12]), em.slots[k].R)  # link frame in the sensor frame
        moment = sp.mT_vec(Rs, zn) if kind == "wrench" else sp.ZERO3
        ns = sp.v_add(sp.v_cross(c, gf), zn if kind == "wrench" else sp.ZERO3)
        return [*sp.mT_vec(Rs, gf), *moment, *gf, *ns]

    has_dir = "force_dir" in kinds
    fm = bilinear(gb, geo, Operand(gz, 7, one=6), len(rws), out, 12, one=has_dir, hint="fm")
    if has_dir:

        def scale(n: int, m: list, g: list) -> list:
            if kinds[slot_of[n]] != "force_dir":
                return list(m[0:12])
            mag = m[0]
            u, d, cu = tuple(g[12:15]), tuple(g[15:18]), tuple(g[18:21])
            return [*sp.v_scale(mag, d), 0.0, 0.0, 0.0, *sp.v_scale(mag, u),
                    *sp.v_scale(mag, cu)]  # fmt: skip

        fm = bilinear(gb, Operand(fm, 13, one=12), geo, len(rws), scale, 12, one=False, hint="fd")
    if known:  # known slots report their given wrench (link frame)
        z = idx["zero"]
        given = [[*(idx["wrench"][k] if j == 0 and kinds[k] == "known" else [z] * 6), *[z] * 6]
                 for j, k in rws]  # fmt: skip
        fm = gb.op("Add", fm, gb.op("Gather", e, gb.i(np.array(given)), axis=0))
    a_rows = actK if ncols == 1 else gb.op("Gather", actK, gb.i(slot_of), axis=0)
    return gb.op("Mul", fm, a_rows)  # inactive slots: zero


def torques(ctx: StepContext, S0: str, F: str) -> str:
    """Joint torques ``tau_c = sum_i mult_i S_i . F_i``, ``(1, nv)``."""
    gb = ctx.gb
    M = np.zeros((ctx.nb * 6, ctx.nv))
    for i, b in enumerate(ctx.em.tree.bodies):
        if b.coord in ctx.coords and b.kind in ("revolute", "prismatic"):
            M[i * 6 : i * 6 + 6, b.coord] += b.mult
    SF = gb.op("Mul", S0, F)
    return gb.op("MatMul", gb.op("Reshape", SF, gb.i([1, ctx.nb * 6])), gb.f(M))


def _covariance(ctx: StepContext, fm: str, e: str, idx: dict) -> str:
    """``cov_k = M_k Sigma M_k^T`` with ``M_k[o, j] = d w_k[o] / d b_j``, ``(1, 36 K)``."""
    gb, K = ctx.gb, ctx.K
    M = gb.op("Slice", fm, gb.i([K]), gb.i([7 * K]), gb.i([0]))  # rows j K + k
    M = gb.op("Slice", M, gb.i([0]), gb.i([6]), gb.i([1]))  # force, moment
    M = gb.op("Transpose", gb.op("Reshape", M, gb.i([6, K, 6])), perm=[1, 2, 0])  # (K, o, j)
    where = np.array([idx["cov"][s.region] for s in ctx.em.slots])
    sig = gb.op("Reshape", gb.op("Gather", e, gb.i(where), axis=0), gb.i([K, 6, 6]))
    cov = gb.op("MatMul", gb.op("MatMul", M, sig), gb.op("Transpose", M, perm=[0, 2, 1]))
    return gb.op("Reshape", cov, gb.i([1, 36 * K]))


def pack(ctx, fm, tau, ranks, resids, actK, status_in, e, idx, states, more=(),
         localized=()) -> StepLayout:  # fmt: skip
    """The packed output ``out (1, O)``: estimates, status; NaN where the status is not 0.

    Args:
        ctx: the graph.
        fm: :func:`contact_wrenches`.
        tau: :func:`torques`.
        ranks: per region ``(1, 1)``.
        resids: per region ``(1, 1)`` residual norms.
        actK: ``(K, 1)`` slot activity.
        status_in: ``(1, 1)`` status bits of the inputs.
        e: the affine entries.
        idx: their indices.
        states: ``[(sensor, (L, H), (1, L H) value)]`` next states of chained recurrent
            corrections.
        more: further outputs ``[([(field, shape)], (1, n) value)]``, NaN where the status is
            not 0 (the online graph's ``ft_model`` and regressors).
        localized: the localization's outputs, as ``more`` (after ``unknowns``; NaN where the
            status is not 0; their own NaN, no localized contact, sets no status bit).

    Returns:
        The output layout (the graph output ``out`` is declared).
    """
    gb, K, S = ctx.gb, ctx.K, ctx.S
    out = StepLayout()
    pieces = []
    fmK = gb.op("Slice", fm, gb.i([0]), gb.i([K]), gb.i([0])) if ctx.flags.covariance else fm
    out.add("fm", (K, 12))
    pieces.append(gb.op("Reshape", fmK, gb.i([1, 12 * K])))
    out.add("joint_torques", (ctx.nv,))
    pieces.append(tau)
    out.add("residual", (S,))
    pieces.append(gb.op("Concat", *resids, axis=1) if S > 1 else resids[0])
    if ctx.flags.covariance:
        out.add("covariance", (K, 6, 6))
        pieces.append(_covariance(ctx, fm, e, idx))
    for fields, value in more:
        for name, shape in fields:
            out.add(name, shape)
        pieces.append(value)
    n_mask = out.size
    # rank is 0 for a frame that is not estimated (the estimator computes it on zeros)
    okf = gb.cast(gb.op("Equal", status_in, gb.f(0.0)))
    out.add("rank", (S,))
    pieces.append(gb.op("Mul", gb.op("Concat", *ranks, axis=1) if S > 1 else ranks[0], okf))
    unk = np.zeros((K, S))
    for k, sl in enumerate(ctx.em.slots):
        unk[k, sl.region] = float(KINDS[sl.kind])
    out.add("unknowns", (S,))
    pieces.append(gb.op("Gemm", actK, gb.f(unk), transA=1) if K else gb.f(np.zeros((1, S))))
    vals = gb.op("Concat", *pieces, axis=1)
    # a non-finite output from valid inputs: vals . 0 is NaN exactly for a NaN or inf (one node)
    nonfin = gb.op("IsNaN", gb.op("MatMul", vals, gb.f(np.zeros((out.size, 1)))))
    n_est = out.size
    for fields, _value in localized:
        for name, shape in fields:
            out.add(name, shape)
    if localized:
        vals = gb.op("Concat", vals, *(value for _, value in localized), axis=1)
    bit = float(Status.OUTPUT_NONFINITE)
    # status_in + bit * okf where nonfin, else status_in (the bit only for valid inputs): one
    # Gemm of the 0/1 flags, alpha = bit (no Where: onnxruntime's costs more than a Cast)
    status = gb.op("Gemm", gb.cast(nonfin), okf, status_in, alpha=bit)
    # NaN outputs where the status is not 0; torques the graph does not compute: NaN always
    always = np.zeros((1, out.size))
    t0 = out.fields["joint_torques"][0]
    always[0, [t0 + c for c in range(ctx.nv) if c not in ctx.coords]] = np.nan
    # as arithmetic: sqrt(status * m) with m = -1 where masked (NaN for a status > 0, -0 for 0),
    # +0 where kept, NaN where always NaN
    m = always.copy()
    m[0, :n_mask] = -1.0
    m[0, n_est:] = -1.0
    m[np.isnan(always)] = np.nan
    pen = gb.op("Sqrt", gb.op("Mul", status, gb.f(m)))
    out.add("status", (1,))
    for sensor, shape, _h in states:
        out.add(state_out(sensor), shape)
    gb.op("Concat", gb.op("Add", vals, pen), status, *(h for _, _, h in states), axis=1, out="out")
    gb.output("out", [1, out.size])
    return out
