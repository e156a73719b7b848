"""The minimum-norm least-squares solve of ``A x = b`` through the Gram matrix, without LAPACK.

The paper's estimate is ``x* = pinv(A) b`` (Del Prete et al. 2012, Sec. 2.2): the least-squares
solution, of minimum norm when ``A`` has fewer independent columns than unknowns. With
``G = A A^T`` (small, ``R x R``: 6 rows per F/T sensor plus one per measured joint torque):

* ``x* = A^T y`` for **any** ``y`` with ``G y = P b``, where ``P`` projects onto ``range(G)``:
  ``null(G) = null(A^T)``, so every such ``y`` gives the same ``A^T y = A^T pinv(G) b``; no
  eigenvectors are needed.
* **Diagonal-pivoted Cholesky** (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd
  ed., Sec. 10.3): ``Pi^T G Pi = L L^T`` with ``L`` of ``r`` columns, the pivot at each step the
  largest remaining diagonal, stopped when it falls below ``rtol * max(diag(G))``; ``r`` is the
  rank. Pivots are chosen with comparisons and selects (no branch), so one instruction stream
  serves every frame, in eager torch, in generated kernels and in ONNX.
* ``P b = L z`` with ``z = argmin |L z - b|``, from modified Gram-Schmidt on ``[L b]`` (backward
  stable for least squares, Bjorck 1967); then ``y`` on the pivot rows solves the triangular
  ``L_1^T y = z`` (``L_1``: the pivot rows of ``L``), ``G y = L L_1^T y = L z = P b``.

**Rank tolerance.** A pivot counts when it exceeds ``rtol`` times the largest diagonal entry of
``G`` (:data:`RANK_RTOL`: 1e-10 in float64, 1e-5 in float32; the default of 6 eps relative to
the largest eigenvalue sat at rounding noise). Since ``G = A A^T`` squares the singular values,
this resolves ratios ``sigma_min / sigma_max`` of ``A`` down to about ``sqrt(rtol)``: 1e-5 in
float64, 3e-3 in float32. Directions weaker than that are treated as unobservable.

**Noise weighting.** With a noise covariance ``Sigma = L L^T`` of the rows (``L`` lower
triangular: per F/T sensor its ``6 x 6`` reading covariance, per measured joint torque its
variance), the same solve runs on the whitened rows ``L^-1 A x = L^-1 b``
(:func:`weighted_solve_program`): ``G~ = L^-1 G L^-T``, ``b~ = L^-1 b``, ``y = L^-T y~``, so that
``x* = A^T y = pinv(L^-1 A) L^-1 b``. That is the weighted least-squares solution, minimising the
Mahalanobis norm ``(A x - b)^T Sigma^-1 (A x - b)`` (maximum likelihood under Gaussian reading
noise), and among the minimisers, which differ by ``null(A)``, the one of minimum Euclidean norm
``|x|`` (the unknowns' own units, N and N m): weighting changes how the residual is measured,
never which directions are unobservable. The rank rule applies to ``G~``. ``Sigma = I`` is the
paper's ``pinv(A) b``.

Everything is written on scalars (:mod:`torchcontact._scalar`); :func:`min_norm_solve` takes
batched tensors, :func:`solve_program` is the scalar form the estimator's kernel inlines, and
:func:`min_norm_solve_eigh` is the LAPACK reference the tests compare with.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchcontact._internal import counts
from torchcontact._scalar import (
    Scalar,
    add,
    div,
    gt,
    logical_and,
    logical_not,
    logical_or,
    mul,
    select,
    sqrt,
    sub,
    sum_,
)

__all__ = [
    "RANK_RTOL",
    "Factorization",
    "MinNormSolution",
    "cho_solve",
    "cholesky",
    "factorize",
    "min_norm_solve",
    "min_norm_solve_eigh",
    "solve_factored",
    "solve_program",
    "tril_solve",
    "triu_t_solve",
    "weighted_solve_program",
    "whiten",
]

#: Default rank tolerance per dtype, relative to the largest diagonal entry of ``G``.
RANK_RTOL: dict[torch.dtype, float] = {torch.float64: 1e-10, torch.float32: 1e-5}


class Factorization(NamedTuple):
    """A diagonal-pivoted Cholesky factorization of ``G`` on scalars.

    Attributes:
        L: ``R`` columns (step order) of ``R`` scalars each, in the original row order.
        pivot: per step, ``R`` one-hot masks of the pivot row.
        ok: per step, the mask "the pivot passed the rank tolerance".
        q: per step, the Gram-Schmidt orthonormal column (``R`` scalars).
        rq: upper-triangular coefficients ``rq[j][k]`` (``j <= k``) of ``L = Q rq``.
        rank: the number of accepted pivots.
    """

    L: list[list[Scalar]]
    pivot: list[list[Scalar]]
    ok: list[Scalar]
    q: list[list[Scalar]]
    rq: list[list[Scalar]]
    rank: Scalar


def _max(a: Scalar, b: Scalar) -> Scalar:
    return select(gt(a, b), a, b)


def factorize(G: Sequence[Sequence[Scalar]], rtol: float) -> Factorization:
    """Pivoted Cholesky of a symmetric positive semi-definite ``G`` (``R x R`` scalars).

    Only the lower triangle of ``G`` is read.

    Args:
        G: ``R`` rows of ``R`` scalars.
        rtol: rank tolerance relative to ``max(diag(G))``.

    Returns:
        The :class:`Factorization`.
    """
    R = len(G)
    res = [[G[max(i, j)][min(i, j)] for j in range(R)] for i in range(R)]  # symmetric copy
    dmax = 0.0
    for i in range(R):
        dmax = _max(G[i][i], dmax)
    tol = mul(dmax, float(rtol))
    avail: list[Scalar] = [True] * R
    L, pivots, oks = [], [], []
    rank: Scalar = 0.0
    for _k in range(R):
        # pivot: the largest remaining diagonal entry (first one on ties)
        m: Scalar = -1.0
        for i in range(R):
            m = select(avail[i], _max(res[i][i], m), m)
        found: Scalar = False
        oh = []
        for i in range(R):
            hit = logical_and(logical_and(avail[i], logical_not(gt(m, res[i][i]))),
                              logical_not(found))  # fmt: skip
            oh.append(hit)
            found = logical_or(found, hit)
        ok = gt(m, tol)
        inv = select(ok, div(1.0, sqrt(select(ok, m, 1.0))), 0.0)
        col = [sum_([select(oh[i], res[j][i], 0.0) for i in range(R)]) for j in range(R)]
        lk = [select(avail[j], mul(col[j], inv), 0.0) for j in range(R)]
        # eliminate: res -= l l^T, the pivot's row and column exactly zero
        for i in range(R):
            for j in range(i + 1):
                v = sub(res[i][j], mul(lk[i], lk[j]))
                v = select(logical_and(avail[i], logical_not(oh[i])), v, 0.0)
                v = select(logical_not(oh[j]), v, 0.0)
                res[i][j] = res[j][i] = v
        avail = [logical_and(avail[i], logical_not(oh[i])) for i in range(R)]
        L.append(lk)
        pivots.append(oh)
        oks.append(ok)
        rank = add(rank, select(ok, 1.0, 0.0))
    # modified Gram-Schmidt on the accepted columns: L = Q rq
    qs: list[list[Scalar]] = []
    rq: list[list[Scalar]] = [[0.0] * R for _ in range(R)]
    for k in range(R):
        v = list(L[k])
        for j in range(k):
            rjk = _dot(qs[j], v)
            rq[j][k] = rjk
            v = [sub(v[i], mul(rjk, qs[j][i])) for i in range(R)]
        nrm = sqrt(_dot(v, v))
        rq[k][k] = nrm
        inv = select(oks[k], div(1.0, select(oks[k], nrm, 1.0)), 0.0)
        qs.append([mul(x, inv) for x in v])
    return Factorization(L, pivots, oks, qs, rq, rank)


def _dot(a: Sequence[Scalar], b: Sequence[Scalar]) -> Scalar:
    return sum_([mul(x, y) for x, y in zip(a, b, strict=True)])


def solve_factored(f: Factorization, b: Sequence[Scalar]) -> list[Scalar]:
    """A ``y`` with ``G y = P_range(G) b`` from a :func:`factorize` result.

    Args:
        f: the factorization of ``G``.
        b: ``R`` scalars.

    Returns:
        ``R`` scalars ``y`` (zero outside the pivot rows); ``A^T y = pinv(A) b``.
    """
    R = len(b)
    # z = argmin |L z - b|: MGS on the augmented column, then rq z = Q^T b
    r = list(b)
    e = []
    for k in range(R):
        ek = _dot(f.q[k], r)
        e.append(ek)
        r = [sub(r[i], mul(ek, f.q[k][i])) for i in range(R)]
    z: list[Scalar] = [0.0] * R
    for k in range(R - 1, -1, -1):
        acc = sub(e[k], sum_([mul(f.rq[k][j], z[j]) for j in range(k + 1, R)]))
        z[k] = select(f.ok[k], div(acc, select(f.ok[k], f.rq[k][k], 1.0)), 0.0)
    # y on the pivot rows: L_1^T y_piv = z with L_1[k', k] = L[k][pivot_k'] (lower triangular)
    l1 = [[sum_([select(f.pivot[kp][i], f.L[k][i], 0.0) for i in range(R)]) for k in range(R)]
          for kp in range(R)]  # fmt: skip
    yp: list[Scalar] = [0.0] * R
    for k in range(R - 1, -1, -1):
        acc = sub(z[k], sum_([mul(l1[kp][k], yp[kp]) for kp in range(k + 1, R)]))
        yp[k] = select(f.ok[k], div(acc, select(f.ok[k], l1[k][k], 1.0)), 0.0)
    return [sum_([select(f.pivot[k][i], yp[k], 0.0) for k in range(R)]) for i in range(R)]


def solve_program(
    G: Sequence[Sequence[Scalar]], b: Sequence[Scalar], rtol: float
) -> tuple[list[Scalar], Scalar, Scalar, Factorization]:
    """Minimum-norm solve on scalars: ``y``, rank, residual ``|b - G y|`` and the factorization."""
    f = factorize(G, rtol)
    y = solve_factored(f, b)
    R = len(b)
    res = [sub(b[i], sum_([mul(G[max(i, j)][min(i, j)], y[j]) for j in range(R)]))
           for i in range(R)]  # fmt: skip
    return y, f.rank, sqrt(_dot(res, res)), f


def cholesky(H: Sequence[Sequence[Scalar]], floor: float = 0.0) -> list[list[Scalar]]:
    """Lower Cholesky factor ``L`` (``H = L L^T``) of a symmetric positive definite ``H``.

    Only the lower triangle of ``H`` is read; constant zeros of ``H`` (a block-diagonal noise
    covariance) fold away. Pivots are floored at ``floor`` (branch-free: a non-positive pivot
    becomes ``floor``; with 0 it gives a zero or non-finite factor).

    Args:
        H: ``n`` rows of ``n`` scalars.
        floor: smallest pivot.

    Returns:
        ``n`` rows of ``n`` scalars, zero above the diagonal.
    """
    n = len(H)
    L: list[list[Scalar]] = [[0.0] * n for _ in range(n)]
    for j in range(n):
        d = sub(H[j][j], sum_([mul(L[j][k], L[j][k]) for k in range(j)]))
        if floor > 0:
            d = select(gt(d, floor), d, floor)
        L[j][j] = sqrt(d)
        inv = div(1.0, L[j][j])
        for i in range(j + 1, n):
            L[i][j] = mul(sub(H[i][j], sum_([mul(L[i][k], L[j][k]) for k in range(j)])), inv)
    return L


def tril_solve(L: Sequence[Sequence[Scalar]], b: Sequence[Scalar]) -> list[Scalar]:
    """``L^-1 b`` for a lower-triangular ``L`` (forward substitution)."""
    n = len(b)
    y: list[Scalar] = [0.0] * n
    for i in range(n):
        y[i] = mul(sub(b[i], sum_([mul(L[i][k], y[k]) for k in range(i)])), div(1.0, L[i][i]))
    return y


def triu_t_solve(L: Sequence[Sequence[Scalar]], b: Sequence[Scalar]) -> list[Scalar]:
    """``L^-T b`` for a lower-triangular ``L`` (back substitution on ``L^T``)."""
    n = len(b)
    x: list[Scalar] = [0.0] * n
    for i in range(n - 1, -1, -1):
        inv = div(1.0, L[i][i])
        x[i] = mul(sub(b[i], sum_([mul(L[k][i], x[k]) for k in range(i + 1, n)])), inv)
    return x


def cho_solve(L: Sequence[Sequence[Scalar]], r: Sequence[Scalar]) -> list[Scalar]:
    """``(L L^T)^-1 r`` from a :func:`cholesky` factor."""
    return triu_t_solve(L, tril_solve(L, r))


def whiten(
    G: Sequence[Sequence[Scalar]], b: Sequence[Scalar], L: Sequence[Sequence[Scalar]]
) -> tuple[list[list[Scalar]], list[Scalar]]:
    """The whitened system ``G~ = L^-1 G L^-T`` (symmetric, full) and ``b~ = L^-1 b``.

    Args:
        G: ``R x R`` scalars, symmetric (the lower triangle is read).
        b: ``R`` scalars.
        L: lower Cholesky factor of the rows' noise covariance.
    """
    R = len(b)
    Gs = [[G[max(i, j)][min(i, j)] for j in range(R)] for i in range(R)]
    N = [tril_solve(L, [Gs[i][j] for i in range(R)]) for j in range(R)]  # N[j] = column j
    # G~ = N L^-T: its column i is L^-1 (row i of N)
    cols = [tril_solve(L, [N[j][i] for j in range(R)]) for i in range(R)]
    Gt = [[cols[max(i, j)][min(i, j)] for j in range(R)] for i in range(R)]
    return Gt, tril_solve(L, b)


def weighted_solve_program(
    G: Sequence[Sequence[Scalar]],
    b: Sequence[Scalar],
    L: Sequence[Sequence[Scalar]],
    rtol: float,
) -> tuple[list[Scalar], Scalar, Scalar, Factorization]:
    """The noise-weighted solve on scalars (see the module docstring).

    Args:
        G: ``R x R`` Gram matrix ``A A^T``.
        b: ``R`` right side.
        L: ``R x R`` lower Cholesky factor of the rows' noise covariance.
        rtol: rank tolerance, relative to ``max(diag(G~))``.

    Returns:
        ``(y, rank, residual, factorization of G~)``: ``A^T y`` is the weighted estimate,
        ``residual = |A x* - b|`` (unweighted, the rows' own units).
    """
    Gt, bt = whiten(G, b, L)
    f = factorize(Gt, rtol)
    yt = solve_factored(f, bt)
    R = len(b)
    rt = [sub(bt[i], sum_([mul(Gt[i][j], yt[j]) for j in range(R)])) for i in range(R)]
    res = [sum_([mul(L[i][k], rt[k]) for k in range(i + 1)]) for i in range(R)]  # b - G y
    return triu_t_solve(L, yt), f.rank, sqrt(_dot(res, res)), f


class MinNormSolution(NamedTuple):
    """Result of :func:`min_norm_solve`.

    Attributes:
        y: ``(*B, R)`` with ``G y = P_range(G) b``.
        rank: ``(*B,)`` int64 rank of ``G``.
        residual: ``(*B,)`` ``|b - G y|`` (``= |A x* - b|``).
    """

    y: Tensor
    rank: Tensor
    residual: Tensor


def min_norm_solve(G: Tensor, b: Tensor, rtol: float | None = None) -> MinNormSolution:
    """Batched minimum-norm solve through pivoted Cholesky (eager torch, exportable ops).

    Args:
        G: ``(*B, R, R)`` symmetric positive semi-definite (a Gram matrix ``A A^T``).
        b: ``(*B, R)``.
        rtol: rank tolerance relative to ``max(diag(G))`` (default :data:`RANK_RTOL`).

    Returns:
        :class:`MinNormSolution`; ``pinv(A) b = A^T y``.

    Example:
        >>> A = torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
        >>> b = torch.tensor([2.0, 3.0], dtype=torch.float64)
        >>> s = min_norm_solve(A @ A.T, b)
        >>> (A.T @ s.y), s.rank  # the minimum-norm solution [1, 3, 1]
        (tensor([1., 3., 1.], dtype=torch.float64), tensor(2))
    """
    R = G.shape[-1]
    if G.shape[-2:] != (R, R) or b.shape[-1] != R:
        raise ValueError(f"G must be (*B, R, R) and b (*B, R); got {tuple(G.shape)}, {b.shape}")
    rtol = RANK_RTOL.get(G.dtype, 1e-10) if rtol is None else rtol
    batch = torch.broadcast_shapes(G.shape[:-2], b.shape[:-1])
    Gs = [[G[..., i, j].expand(batch) for j in range(R)] for i in range(R)]
    bs = [b[..., i].expand(batch) for i in range(R)]
    y, rank, res, _ = solve_program(Gs, bs, rtol)

    def t(x: Scalar) -> Tensor:
        return x if isinstance(x, Tensor) else G.new_full(batch, float(x))

    return MinNormSolution(torch.stack([t(v) for v in y], -1), counts(t(rank)), t(res))


def min_norm_solve_eigh(G: Tensor, b: Tensor, rtol: float | None = None) -> MinNormSolution:
    """The same solve through LAPACK ``eigh`` (a test reference; not exportable).

    Eigenvalues below ``rtol * max(diag(G))`` count as zero, like :func:`min_norm_solve`'s pivots.
    """
    rtol = RANK_RTOL.get(G.dtype, 1e-10) if rtol is None else rtol
    lam, V = torch.linalg.eigh(G)
    dmax = torch.diagonal(G, dim1=-2, dim2=-1).amax(-1, keepdim=True)
    keep = lam > rtol * dmax
    inv = torch.where(keep, 1.0 / torch.where(keep, lam, torch.ones_like(lam)), 0.0)
    y = (V * inv.unsqueeze(-2)) @ (V.transpose(-1, -2) @ b.unsqueeze(-1))
    y = y.squeeze(-1)
    res = (b - (G @ y.unsqueeze(-1)).squeeze(-1)).norm(dim=-1)
    return MinNormSolution(y, keep.sum(-1), res)
