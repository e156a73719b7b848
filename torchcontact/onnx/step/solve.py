"""Stage 4 of the single-frame graph: the minimum-norm least-squares solve of one region.

:mod:`torchcontact.solve`'s rule (diagonal-pivoted, the pivot the first largest remaining
diagonal, accepted above ``rtol * max(diag G)``), as Gauss-Jordan elimination on ``[G | I | b]``:
after the accepted pivots it holds ``G11^{-1}``, ``C = G21 G11^{-1}`` and ``G11^{-1} b1``. The
least-squares part (``b`` outside the range of ``G``) is the projection on ``range([I; C])``:
``y1 = G11^{-1} (b1 + C^T s)`` with ``(I + C C^T) s = b2 - C b1``, a well-conditioned system over
the rejected pivots, eliminated the same way. Same pivots, same rank and the same minimum-norm
solution as :func:`torchcontact.solve.solve_program` (it only replaces the Gram-Schmidt fix-up by
this projection); no linear-algebra ops, no atan.

**Noise weighting** (a graph exported with ``ft_noise``): the rows are whitened by constants,
``G~ = W G W``, ``b~ = W b`` with ``W = diag(1 / sigma)`` (per sensor row its reading's standard
deviation, per torque row 1), the same elimination runs on ``G~`` (the rank rule on its
diagonal) and ``y = W y~``: :func:`torchcontact.solve.weighted_solve_program` with a diagonal
noise factor ``L = W^-1``, the weighted least-squares solution of minimum Euclidean norm.

**Full-rank frames** take a shorter road (about 40 nodes instead of 110 on six rows): when the
frame's active slots can give rank ``R`` (:func:`full_rank_possible`, decided per frame), the
sweep operator runs unpivoted on ``G`` (Jacobi-scaled in a noise-weighted graph, whose
whitened rows spread over decades; five nodes a pivot, no pivot search),
giving ``G^-1``. Every pivot the pivoted rule can meet, in any order, is a Schur complement's
diagonal entry, at least ``1 / (G^-1)_ii``; so when ``1 / (G^-1)_ii > rtol max diag G`` for
every ``i`` the pivoted elimination would accept all ``R`` pivots and its result is
``y = G^-1 rhs``, which is returned. Otherwise (or when the frame cannot have full rank) the
pivoted elimination runs, in the other branch of an ``If``. The sweep itself runs on every
frame in the main graph (a frame that cannot have full rank discards it): one ``If`` per
region, not two nested ones (each ``If`` costs onnxruntime a subgraph call, as much as
several plain nodes). A layout that never has full rank (two point forces on one sensor) builds the
pivoted elimination alone.
"""

from __future__ import annotations

import numpy as np

from torchcontact.contacts import KINDS
from torchcontact.estimation.layout import Region
from torchcontact.onnx.builder import onnx_type
from torchcontact.onnx.step.context import StepContext

__all__ = ["full_rank_possible", "min_rank", "solve_region"]

#: Magnitude marking used pivots in the elimination (a power of two: scaling by it is exact).
_BIG = {np.dtype(np.float64): 2.0**600, np.dtype(np.float32): 2.0**100}  # > any diagonal


def min_rank(ctx: StepContext, reg: Region) -> int:
    """Smallest rank of ``G`` with one active slot (force_dir 1, force 3, wrench 6)."""
    ranks = {"force_dir": 1, "force": 3, "wrench": 6}
    vals = [ranks[ctx.em.slots[k].kind] for k in reg.slots if ctx.em.slots[k].kind in ranks]
    return min(vals) if vals else 0


def solve_region(ctx: StepContext, G: str, b: str, R: int, r_min: int, ncols: int,
                 w: np.ndarray | None = None, possible: str | None = None):  # fmt: skip
    """Minimum-norm least-squares ``y`` (``(R, ncols)``) and rank (``(1, 1)``) of one region.

    Gauss-Jordan elimination of ``[G | I | b]`` with :mod:`torchcontact.solve`'s pivots: at each
    step the first largest remaining diagonal, accepted when above ``rtol * max diag``. A second
    elimination over the rejected pivots projects ``b`` on the range of ``G``. With ``possible``,
    a frame that may have full rank first tries the unpivoted sweep (module doc), which ends
    there when it proves full rank.

    Args:
        ctx: the graph.
        G: ``(R, R)`` Gram matrix.
        b: ``(R, 1)`` right side.
        R: rows.
        r_min: the rank when any slot is active (the projection is skipped when it is ``R``).
        ncols: 1, or 7 with the covariance (``d y / d b_j`` for the 6 sensor rows follow ``y``).
        w: ``(R,)`` the rows' whitening ``1 / sigma`` (the weighted solve), None: unweighted.
        possible: :func:`full_rank_possible` (None: the pivoted elimination only).
    """
    gb = ctx.gb
    if w is None:
        return _solve(ctx, G, b, R, r_min, ncols, None, possible)
    # whiten: G~ = W G W, b~ = W b; y = W y~. A float32 graph eliminates in float64 here: the
    # whitened system's spread of scales costs the float32 elimination up to 2.5e-2 of the
    # forces (measured on the bundled arm; the unweighted one 7e-6, the batched graph 8e-5)
    graph_dtype = gb.dtype
    wide = graph_dtype != np.float64
    if wide:
        G, b = (gb.op("Cast", v, to=onnx_type(np.float64)) for v in (G, b))
        gb.dtype = np.dtype(np.float64)
    try:
        Gw, bw = gb.op("Mul", G, gb.f(np.outer(w, w))), gb.op("Mul", b, gb.f(w[:, None]))
        y, rank = _solve(ctx, Gw, bw, R, r_min, ncols, w[:6, None], possible, graph_dtype)
        y = gb.op("Mul", y, gb.f(w[:, None]))
    finally:
        gb.dtype = graph_dtype
    if wide:
        y, rank = gb.cast(y), gb.cast(rank)
    return y, rank


def full_rank_possible(ctx: StepContext, reg: Region, R: int, act: str) -> str | None:
    """A necessary condition for rank ``R`` on this frame, or None: never.

    Rank ``R`` needs at least ``R`` unknowns of active slots, and the sensor's six rows need a
    wrench slot or point forces at three points or more (at one or two points they span at most
    3 or 5 directions of wrenches). Returned as a ``(1, 1)`` count, ``>= 0``, that is above 2.5
    exactly when the condition holds (:func:`solve_region` folds the test into its own).

    Args:
        ctx: the graph.
        reg: the region.
        R: its rows.
        act: ``(K, 1)`` 0/1 slot activity.
    """
    kinds = {k: ctx.em.slots[k].kind for k in reg.slots}
    M = np.zeros((ctx.K, 3))  # per slot: unknowns, a wrench, a point force
    for k, kind in kinds.items():
        M[k] = (KINDS[kind], kind == "wrench", kind in ("force", "force_dir"))
    most = M.sum(0)
    if most[0] < R or not (most[1] >= 1 or most[2] >= 3):
        return None
    gb = ctx.gb
    if R == 6 and "force_dir" not in kinds.values():
        # a wrench (6 unknowns) or three forces (9) have the unknowns: one count decides
        return gb.op("Gemm", act, gb.f(M[:, 1:2] * 3.0 + M[:, 2:3]), transA=1)
    v = gb.op("Gemm", act, gb.f(M), transA=1)  # (1, 3) over the active slots
    g = gb.cast(gb.op("Greater", v, gb.f([[R - 0.5, 0.5, 2.5]])))
    return gb.op("MatMul", g, gb.f([[2.0], [1.0], [1.0]]))  # 3 or 4 when possible


def _solve(ctx: StepContext, G: str, b: str, R: int, r_min: int, ncols: int,
           w6: np.ndarray | None = None, possible: str | None = None,
           pdtype=None):  # fmt: skip
    """:func:`solve_region` on (whitened) ``G``, ``b``; ``w6``: the unit right sides' whitening.

    ``pdtype``: the dtype of ``possible``'s count (None: the elimination's own).

    With ``possible`` (:func:`full_rank_possible`), the unpivoted sweep runs first: on a frame
    that may have full rank and where it proves every pivot of any order accepted,
    ``y = G^-1 rhs`` from it (:func:`_sweep`); any other frame runs the pivoted elimination
    (:func:`_pivoted`), in the other branch of the one ``If``.
    """
    gb = ctx.gb
    rhs = b
    if ncols > 1:  # unit right sides for the covariance: d y / d b_j, j < 6
        E6 = np.zeros((R, 6))
        E6[:6, :6] = np.eye(6) if w6 is None else np.diag(w6[:, 0])
        rhs = gb.op("Concat", b, gb.f(E6), axis=1)
    if possible is None:
        return _pivoted(ctx, G, rhs, R, r_min, ncols)
    # the rank rule: a pivot counts above rtol times the largest diagonal of G
    jacobi = w6 is not None
    if jacobi:  # the diagonal scales the sweep: in the main graph
        d0 = gb.op("GatherElements", G, gb.i(np.arange(R)[:, None]), axis=1)
        dmax = gb.op("ReduceMax", d0, keepdims=1)
        tol = gb.op("Mul", dmax, gb.f([[ctx.em.rank_rtol]]))
    else:
        # the unweighted sweep's test compares against the largest entry of G, which is its
        # largest diagonal entry (G is a Gram matrix: |G_ij| <= sqrt(G_ii G_jj)), with rtol
        # folded into a constant; the pivoted branch takes the diagonal and tol itself
        d0, tol = None, None
        dmax = gb.op("ReduceMax", G, keepdims=1)

    def pivoted() -> list[str]:
        return list(_pivoted(ctx, G, rhs, R, r_min, ncols, d0, tol))

    # the sweep runs on every frame, in the main graph (on a frame that cannot have full rank
    # its values are discarded): one If instead of two nested ones, each of which costs
    # onnxruntime a subgraph call per frame
    ok, solve_full = _sweep(ctx, G, rhs, R, d0, dmax if tol is None else tol, jacobi)
    # the If's condition: every pivot accepted (ok) and full rank possible (its count > 2.5),
    # as min_i (ok_i ? count : 0) > 2.5 (the count is >= 0), in the count's dtype
    count_dtype = ctx.dtype if pdtype is None else np.dtype(pdtype)
    zero = gb.const(np.zeros(1), count_dtype)
    least = gb.op("ReduceMin", gb.op("Where", ok, possible, zero), keepdims=0)
    cond = gb.op("Greater", least, gb.const(np.full(1, 2.5), count_dtype))
    fast = gb.branch(lambda: [solve_full(), gb.f([[float(R)]])], "full_rank")
    y, rank = gb.op("If", cond, n_out=2, then_branch=fast,
                    else_branch=gb.branch(pivoted, "pivoted"))  # fmt: skip
    return y, rank


def _sweep(ctx: StepContext, G: str, rhs: str, R: int, d0: str | None, tol: str,
           jacobi: bool = True):  # fmt: skip
    """The unpivoted sweep: ``(ok, solve)``.

    ``ok``: ``(R, 1)`` bool, for each ``i`` whether ``1 / (G^-1)_ii`` is above the rank rule's
    threshold; all true: the pivoted rule accepts every pivot whatever the order. ``tol`` is
    that threshold with ``jacobi``, else the largest diagonal of ``G`` (the threshold over
    ``rtol``: ``rtol / (G^-1)_ii > max diag G``, the product by ``rtol`` folded into a
    constant). ``solve()`` emits ``y = G^-1 rhs``, from the sweep operator on ``G``,
    Jacobi-scaled with ``jacobi`` (the whitened systems: their rows' scales spread over decades;
    an unweighted ``G`` is swept as it is, five nodes fewer).
    """
    gb = ctx.gb
    diag = gb.i(np.arange(R)[:, None])
    A = G
    if jacobi:
        # Jacobi scaling first, G' = D G D with D = diag(d0)^-1/2 (unit diagonal: the unpivoted
        # sweep below is then as accurate as the pivoted elimination on badly scaled, whitened G)
        sc = gb.op("Sqrt", d0)  # D^-1
        A = gb.op("Div", G, gb.op("Gemm", sc, sc, transB=1))
    # the sweep operator (Goodnight 1979) on every index in order: A <- A - a a^T / d with
    # a = A e_k - e_k, d = A_kk, which is the sweep but for -2 on the swept diagonal entry; those
    # offsets are never read again (column k is read only at step k), so they are added at the
    # end: the result is 2 I - G'^-1 (G' = G unscaled)
    eye = np.eye(R)
    for k in range(R):
        c = gb.op("Gather", A, gb.i([k]), axis=1)
        a = gb.op("Sub", c, gb.f(eye[:, k : k + 1]))
        d = gb.op("Gather", c, gb.i([k]), axis=0)
        A = gb.op("Gemm", gb.op("Div", a, d), a, A, alpha=-1.0, transB=1)
    # full rank for the pivoted rule whatever the pivot order when 1 / (G^-1)_ii > tol for every
    # i: each pivot the elimination can meet, a Schur complement's diagonal entry, is at least
    # 1 / (G^-1)_ii (eliminating more only lowers it); 1 / (G^-1)_ii = d0_i / (G'^-1)_ii. NaN
    # (a zero diagonal or pivot met here) fails.
    h = gb.op("Sub", gb.f(2.0), gb.op("GatherElements", A, diag, axis=1))  # (G'^-1)_ii
    inv = gb.op("Div", d0 if jacobi else gb.f(1.0 / ctx.em.rank_rtol), h)
    ok = gb.op("Greater", inv, tol)

    def solve() -> str:  # y = D G'^-1 D rhs
        if not jacobi:
            return gb.op("Gemm", A, rhs, rhs, alpha=-1.0, beta=2.0)
        u = gb.op("Div", rhs, sc)
        return gb.op("Div", gb.op("Gemm", A, u, u, alpha=-1.0, beta=2.0), sc)

    return ok, solve


def _pivoted(ctx: StepContext, G: str, rhs: str, R: int, r_min: int, ncols: int,
             d0: str | None = None, tol: str | None = None):  # fmt: skip
    """The pivoted Gauss-Jordan elimination and the least-squares projection (module doc).

    ``rhs`` ``(R, ncols)``; ``d0`` the diagonal of ``G`` ``(R, 1)`` and ``tol`` the rank rule's
    threshold ``(1, 1)`` when computed already.
    """
    gb = ctx.gb
    big = _BIG[ctx.dtype]
    eye = np.eye(R)
    Wc = 2 * R + ncols
    top = gb.op("Concat", G, gb.f(eye), rhs, axis=1)
    # rows R..2R-1 hold -I in the pivot columns: gathering column p gives [c; -e_p]
    bottom = np.zeros((R, Wc))
    bottom[:, :R] = -eye
    W = gb.op("Concat", top, gb.f(bottom), axis=0)
    J = np.zeros((2 * R, 2 * R))  # [c; -e_p] -> [c - e_p; 0]
    J[:R, :R] = eye
    J[:R, R:] = eye
    P = np.zeros((2 * R, 2 * R))  # [c; -e_p] -> [-big e_p; 0]: the used-pivot penalty
    P[:R, R:] = eye * big
    if d0 is None:
        d0 = gb.op("GatherElements", W, gb.i(np.arange(R)[:, None]), axis=1)
        # the rank rule: a pivot counts above rtol times the largest diagonal of G
        tol = gb.op("Mul", gb.op("ReduceMax", d0, keepdims=1), gb.f([[ctx.em.rank_rtol]]))
    dm = gb.op("Concat", d0, gb.f(np.full((R, 1), -big)), axis=0)
    pivots, oks = [], []
    for k in range(R):
        p = gb.op("ArgMax", dm, axis=0, keepdims=0)  # first largest: solve.py's tie rule
        m = gb.op("ReduceMax", dm, keepdims=1)
        c2 = gb.op("Gather", W, p, axis=1)  # (2R, 1)
        ok = gb.op("Greater", m, tol)
        f = gb.op("Where", ok, gb.op("Div", gb.op("MatMul", gb.f(J), c2), m), gb.f(0.0))
        row = gb.op("Gather", W, p, axis=0)
        W = gb.op("Gemm", f, row, W, alpha=-1.0, beta=1.0)
        if k < R - 1:
            dm = gb.op("Gemm", gb.f(P), c2, gb.op("Sub", dm, gb.op("Mul", f, c2)))
        pivots.append(p)
        oks.append(ok)
    # accepted rows (a column), rank
    okc = gb.cast(gb.op("Concat", *oks, axis=0))  # (R, 1) per step
    rank = gb.op("ReduceSum", okc, keepdims=1)
    perm = gb.op("Gather", gb.f(eye), gb.op("Concat", *pivots, axis=0), axis=0)  # row k: e_pk
    acc = gb.op("Gemm", perm, okc, transA=1)  # (R, 1)
    Wr = gb.op("Slice", W, gb.i([0, R]), gb.i([R, 2 * R]), gb.i([0, 1]))  # G11^-1 | -C, I
    b_all = gb.op("Slice", W, gb.i([0, 2 * R]), gb.i([R, Wc]), gb.i([0, 1]))
    Wacc = gb.op("Mul", Wr, acc)
    if r_min >= R:  # always full rank when any slot is active
        return gb.op("MatMul", Wacc, rhs), rank
    # least squares: (I + C C^T) s = b2 - C b1 over the rejected pivots (they follow the
    # accepted ones); the rejected rows of Wr are [-C, I], so Wr Wr^T holds I + C C^T there
    K2 = gb.op("Gemm", Wr, Wr, transB=1)
    V = gb.op("Concat", gb.op("Concat", K2, b_all, axis=1),
              gb.f(np.concatenate([-eye, np.zeros((R, ncols))], axis=1)), axis=0)  # fmt: skip
    for k in range(max(r_min, 1), R):
        c2 = gb.op("Gather", V, pivots[k], axis=1)
        piv = gb.op("Gather", c2, pivots[k], axis=0)
        f = gb.op("Where", oks[k], gb.f(0.0), gb.op("Div", gb.op("MatMul", gb.f(J), c2), piv))
        row = gb.op("Gather", V, pivots[k], axis=0)
        V = gb.op("Gemm", f, row, V, alpha=-1.0, beta=1.0)
    s = gb.op("Slice", V, gb.i([0, R]), gb.i([R, R + ncols]), gb.i([0, 1]))
    s_rej = gb.op("Sub", s, gb.op("Mul", s, acc))
    # y = G11^-1 (b1 + C^T s) = Wacc (b - Wr^T s_rej)
    t = gb.op("Gemm", Wr, s_rej, rhs, alpha=-1.0, beta=1.0, transA=1)
    return gb.op("MatMul", Wacc, t), rank
