"""Friction-cone constrained least squares: contact forces that push, within their cones.

The paper's estimate ``x* = pinv(A) b`` (:mod:`torchcontact.solve`) spreads the measured wrench
over every contact and may pull. Its conclusion (Del Prete et al. 2012, Sec. 3) names the remedy:
contact forces push and are quasi-normal to the skin, so each force can be confined to a cone
around the surface normal. This module solves, per frame and region,

.. code-block:: text

    minimise    1/2 |A x - b|^2 + eps/2 |x|^2
    subject to  C_k x  in  Q^3      for every constrained slot k,

where ``Q^3 = {(t, y) : |y| <= t}`` is the second-order cone and ``C_k`` maps the unknowns to
the slot's cone coordinates ``(mu (-n . f), t1 . f, t2 . f)`` (:func:`cone_rows`): the force
``f`` (of a pure-force slot, or the force part of a full wrench) lies in the friction cone of
coefficient ``mu`` around the inward direction ``-n`` of the outward surface normal ``n``. A
``force_dir`` slot (magnitude ``lam`` along a given direction) pushes when ``lam >= 0``
(``C_k = [1, 0, 0]^T``). ``eps > 0`` makes the minimiser unique: among the solutions of the
constrained least-squares problem, the one of (nearly) minimum norm, so that an unconstrained
minimiser inside every cone is the pseudo-inverse solution (to ``O(eps / sigma_min^2)``).

**Algorithm: a primal-dual interior-point method with a fixed iteration budget.** Mehrotra
predictor-corrector steps (Mehrotra 1992) with Nesterov-Todd scaling of the second-order cones
(Nesterov & Todd 1997; the formulation of Vandenberghe, *The CVXOPT linear and quadratic cone
program solvers*, 2010, Sec. 5-6, as used by ECOS and Clarabel). Each iteration factors the
``u x u`` Newton matrix ``A^T A + eps I + sum_k C_k^T W_k^{-2} C_k`` once (plain Cholesky: it is
positive definite) and solves it for the predictor and the corrector right sides. Why this, for
batched small problems (``u`` = 3 to 18 unknowns, 1 to 6 cones, millions of frames):

* **Accuracy at a fixed budget, from a cold start.** The iteration count of an interior-point
  method hardly depends on the data: 20 to 30 iterations reach 1e-9 relative accuracy on these
  problems whatever their conditioning. First-order methods (ADMM on the same normal equations,
  projected gradient) converge linearly at a rate set by the conditioning of ``A`` and the angle
  between the cones and ``null(A)``; the estimator's matrices are rank-deficient by design
  (that is why the cones are needed), and ADMM typically needs hundreds of iterations for 1e-6
  here. A fixed budget is what makes the program straight-line code (exportable, one
  instruction stream for every frame on SIMD lanes or CUDA threads), so the method whose budget
  can be small and data-independent wins.
* **Cost.** One ``u x u`` Cholesky per iteration (about ``u^3 / 6`` multiply-adds: 288 for four
  pure forces) is cheap next to the RNEA of a humanoid; ``A^T A`` and the constant parts
  ``C_k^T J C_k`` are formed once per frame.
* **Branch-free.** Step lengths to the cone boundaries have closed forms; every choice is a
  ``select``. A frame stops moving once its duality gap reaches rounding level
  (:data:`FREEZE_GAP`), and a step that would make the iterate non-finite is not taken. Each
  Mehrotra step is compared with the same step without the second-order term and the one that
  lowers the gap more is kept: Mehrotra's term alone cycled on frames whose solution is at the
  cones' apexes.

**Warm start.** ``x0`` is the starting point (the pseudo-inverse solution by default, or the
previous frame's estimate). When it lies inside every cone it is returned as it is: the
pseudo-inverse solution is the ``eps -> 0`` limit of the unconstrained problem, which the
iterates approach only to rounding / ``eps`` along ``null(A)``. The slacks start at ``C_k x0``
moved inside the cones and the duals at a multiple of the cone's centre, as interior-point
methods require (the dual of the previous frame is not reused: a point on the cone boundary is
a poor start).

**Status per frame.** ``converged`` (the residuals and the duality gap meet ``tol``),
``iterations`` (the iteration at which they first did; the budget otherwise) and per cone
``active`` (the constraint binds: the force is on the cone's boundary, or at its apex, to
within ``10 tol`` relative).

Everything is written on scalars (:mod:`torchcontact._scalar`): it runs eagerly on ``(N,)``
tensors (CPU, CUDA, ONNX export) and inside generated kernels. :func:`cone_constrained_lstsq` is
the batched tensor form used by tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from torchcontact._scalar import (
    Scalar,
    add,
    div,
    gt,
    isfinite,
    logical_and,
    logical_not,
    logical_or,
    mul,
    neg,
    select,
    sqrt,
    sub,
    sum_,
)
from torchcontact.errors import InputError

__all__ = [
    "DEFAULT_EPS",
    "DEFAULT_TOL",
    "Cone",
    "ConeSolution",
    "FrictionCones",
    "cone_constrained_lstsq",
    "cone_rows",
    "solve_cones",
]

#: Default regularisation ``eps`` per dtype (``A`` has entries of order 1 and metres).
DEFAULT_EPS: dict[torch.dtype, float] = {torch.float64: 1e-9, torch.float32: 1e-5}
#: A frame stops moving once its duality gap is below this, relative to ``1 + |A^T b|^2``.
FREEZE_GAP = 1e-16
#: Default convergence tolerance per dtype (relative residuals and gap).
DEFAULT_TOL: dict[torch.dtype, float] = {torch.float64: 1e-6, torch.float32: 1e-3}


@dataclass(frozen=True)
class FrictionCones:
    """Settings of the friction-cone constrained estimate (``estimate(..., constraints=...)``).

    The cones themselves (normals, friction coefficients, which slots push) are per slot in
    :class:`~torchcontact.Contacts`.

    Attributes:
        iterations: fixed interior-point iteration budget (straight-line code; 20 reached
            1e-9 on every tested problem, 7 to 9 iterations typically).
        eps: regularisation ``eps`` of ``|A x - b|^2 + eps |x|^2`` (default
            :data:`DEFAULT_EPS` of the model's dtype).
        tol: convergence tolerance of the ``converged`` flag (default :data:`DEFAULT_TOL`).

    Example:
        >>> FrictionCones(iterations=30).iterations
        30
    """

    iterations: int = 20
    eps: float | None = None
    tol: float | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.iterations, int) and 1 <= self.iterations <= 200):
            raise InputError(f"FrictionCones.iterations must be an int in [1, 200], got "
                             f"{self.iterations!r}")  # fmt: skip
        for name in ("eps", "tol"):
            v = getattr(self, name)
            if v is not None and not (float(v) > 0 and float(v) < 1):
                raise InputError(f"FrictionCones.{name} must be in (0, 1), got {v!r}")

    def resolved(self, dtype: torch.dtype) -> tuple[int, float, float]:
        """``(iterations, eps, tol)`` with the defaults of ``dtype`` filled in."""
        eps = DEFAULT_EPS.get(dtype, 1e-9) if self.eps is None else float(self.eps)
        tol = DEFAULT_TOL.get(dtype, 1e-9) if self.tol is None else float(self.tol)
        return self.iterations, eps, tol


class Cone(NamedTuple):
    """One second-order cone constraint ``C x[cols] in Q^3`` of :func:`solve_cones`.

    Attributes:
        cols: indices of the unknowns it reads (one slot's).
        C: 3 rows of ``len(cols)`` scalars: the cone coordinates ``(t, y1, y2)`` of the slot.
        on: mask scalar: the constraint applies in this frame (else it is ignored).
    """

    cols: tuple[int, ...]
    C: list[list[Scalar]]
    on: Scalar


class ConeSolution(NamedTuple):
    """Result of :func:`solve_cones` (scalars).

    Attributes:
        x: ``u`` unknowns.
        converged: mask: residuals and gap met the tolerance within the budget.
        iterations: the iteration at which the duality gap first met the tolerance (the budget
            if never), as a float.
        active: per cone, mask: the constraint binds at the solution.
    """

    x: list[Scalar]
    converged: Scalar
    iterations: Scalar
    active: list[Scalar]


# ----------------------------------------------------------------------- small dense algebra


def _dot(a: Sequence[Scalar], b: Sequence[Scalar]) -> Scalar:
    return sum_([mul(x, y) for x, y in zip(a, b, strict=True)])


def _max(a: Scalar, b: Scalar) -> Scalar:
    return select(gt(a, b), a, b)


def _cholesky(H: list[list[Scalar]], floor: float) -> list[list[Scalar]]:
    """Lower Cholesky factor of a symmetric positive definite ``H`` (pivots floored)."""
    n = len(H)
    L: list[list[Scalar]] = [[0.0] * n for _ in range(n)]
    for j in range(n):
        d = sub(H[j][j], sum_([mul(L[j][k], L[j][k]) for k in range(j)]))
        d = select(gt(d, floor), d, floor)
        ljj = sqrt(d)
        inv = div(1.0, ljj)
        L[j][j] = ljj
        for i in range(j + 1, n):
            L[i][j] = mul(sub(H[i][j], sum_([mul(L[i][k], L[j][k]) for k in range(j)])), inv)
        L[j] = L[j]  # row j complete up to the diagonal
    return L


def _cho_solve(L: list[list[Scalar]], r: Sequence[Scalar]) -> list[Scalar]:
    """``(L L^T)^{-1} r``."""
    n = len(r)
    y: list[Scalar] = [0.0] * n
    for i in range(n):
        y[i] = div(sub(r[i], sum_([mul(L[i][k], y[k]) for k in range(i)])), L[i][i])
    x: list[Scalar] = [0.0] * n
    for i in range(n - 1, -1, -1):
        x[i] = div(sub(y[i], sum_([mul(L[k][i], x[k]) for k in range(i + 1, n)])), L[i][i])
    return x


# ------------------------------------------------------------------ second-order cone algebra
# A cone vector is (v0, v1, v2): v0 the axis, (v1, v2) the disc. J = diag(1, -1, -1).


def _jdot(a: Sequence[Scalar], b: Sequence[Scalar]) -> Scalar:
    """``a^T J b``."""
    return sub(mul(a[0], b[0]), add(mul(a[1], b[1]), mul(a[2], b[2])))


def _eig_min(v: Sequence[Scalar]) -> Scalar:
    """Smallest Jordan eigenvalue ``v0 - |v1|`` (>= 0 inside the cone)."""
    return sub(v[0], sqrt(add(mul(v[1], v[1]), mul(v[2], v[2]))))


class _Scaling(NamedTuple):
    """Nesterov-Todd scaling ``W = eta Wbar(w)`` of one cone (``W z = W^{-1} s = lam``)."""

    eta: Scalar
    w: list[Scalar]  # w^T J w = 1, w0 > 0


def _nt_scaling(s: Sequence[Scalar], z: Sequence[Scalar]) -> _Scaling:
    ns = sqrt(_jdot(s, s))
    nz = sqrt(_jdot(z, z))
    sb = [div(v, ns) for v in s]
    zb = [div(v, nz) for v in z]
    gamma = sqrt(mul(add(1.0, _dot(sb, zb)), 0.5))
    inv2g = div(0.5, gamma)
    w = [mul(add(sb[0], zb[0]), inv2g), mul(sub(sb[1], zb[1]), inv2g),
         mul(sub(sb[2], zb[2]), inv2g)]  # fmt: skip
    return _Scaling(sqrt(div(ns, nz)), w)


def _w_apply(sc: _Scaling, v: Sequence[Scalar], inverse: bool) -> list[Scalar]:
    """``W v`` (or ``W^{-1} v``): ``Wbar = [[w0, w1^T], [w1, I + w1 w1^T / (1 + w0)]]``."""
    w = sc.w
    w1v1 = add(mul(w[1], v[1]), mul(w[2], v[2]))
    if inverse:  # Wbar^{-1} = J Wbar J
        first = sub(mul(w[0], v[0]), w1v1)
        coef = sub(div(w1v1, add(1.0, w[0])), v[0])
        scale = div(1.0, sc.eta)
    else:
        first = add(mul(w[0], v[0]), w1v1)
        coef = add(div(w1v1, add(1.0, w[0])), v[0])
        scale = sc.eta
    out = [first, add(v[1], mul(coef, w[1])), add(v[2], mul(coef, w[2]))]
    return [mul(scale, x) for x in out]


def _w_inv2(sc: _Scaling, v: Sequence[Scalar]) -> list[Scalar]:
    """``W^{-2} v = eta^{-2} (2 wh wh^T - J) v`` with ``wh = J w``."""
    wh = (sc.w[0], neg(sc.w[1]), neg(sc.w[2]))
    t = mul(2.0, _dot(wh, v))
    inv = div(1.0, mul(sc.eta, sc.eta))
    return [mul(inv, sub(mul(t, wh[0]), v[0])), mul(inv, add(mul(t, wh[1]), v[1])),
            mul(inv, add(mul(t, wh[2]), v[2]))]  # fmt: skip


def _jordan(a: Sequence[Scalar], b: Sequence[Scalar]) -> list[Scalar]:
    """Jordan product ``a o b = (a^T b, a0 b1 + b0 a1)``."""
    return [_dot(a, b), add(mul(a[0], b[1]), mul(b[0], a[1])),
            add(mul(a[0], b[2]), mul(b[0], a[2]))]  # fmt: skip


def _jordan_solve(lam: Sequence[Scalar], v: Sequence[Scalar]) -> list[Scalar]:
    """``u`` with ``lam o u = v`` (``lam`` inside the cone)."""
    l1v1 = add(mul(lam[1], v[1]), mul(lam[2], v[2]))
    u0 = div(sub(mul(lam[0], v[0]), l1v1), _jdot(lam, lam))
    inv0 = div(1.0, lam[0])
    return [u0, mul(sub(v[1], mul(u0, lam[1])), inv0), mul(sub(v[2], mul(u0, lam[2])), inv0)]


def _inv_max_step(x: Sequence[Scalar], d: Sequence[Scalar]) -> Scalar:
    """``1 / max{a : x + a d in Q}`` (0 when unbounded), for ``x`` inside the cone.

    With ``H`` the hyperbolic reflection taking ``x / nu`` to the cone's centre
    (``nu = sqrt(x^T J x)``), ``x + a d`` stays inside while ``nu + a lam_min(H d) >= 0``.
    """
    nu = sqrt(_jdot(x, x))
    inv_nu = div(1.0, nu)
    xb = [mul(v, inv_nu) for v in x]
    r0 = _jdot(xb, d)
    c = div(add(d[0], r0), add(1.0, xb[0]))
    r1 = (sub(d[1], mul(c, xb[1])), sub(d[2], mul(c, xb[2])))
    neg_eig = sub(sqrt(add(mul(r1[0], r1[0]), mul(r1[1], r1[1]))), r0)
    return mul(_max(neg_eig, 0.0), inv_nu)


# ----------------------------------------------------------------------------------- the solver


def _cx(c: Cone, x: Sequence[Scalar]) -> list[Scalar]:
    """The cone coordinates ``C x[cols]``."""
    return [_dot(row, [x[i] for i in c.cols]) for row in c.C]


def _ct(c: Cone, v: Sequence[Scalar]) -> list[Scalar]:
    """``C^T v`` (one entry per column of the cone)."""
    return [sum_([mul(c.C[r][j], v[r]) for r in range(3)]) for j in range(len(c.cols))]


def _on3(o: Scalar, v: Sequence[Scalar], off: Sequence[Scalar]) -> list[Scalar]:
    return [select(o, a, b_) for a, b_ in zip(v, off, strict=True)]


def _newton(cones, on, L, rd, rp, scs, v) -> tuple[list, list, list]:
    """Newton direction for ``lam o (W dz + W^-1 ds) = lam o v`` (``v`` per cone).

    Eliminating ``ds = C dx + r_p`` and ``dz = W^-1 v - W^-2 (C dx + r_p)`` leaves
    ``H dx = -r_d + sum_k C_k^T (W_k^-1 v_k - W_k^-2 r_p,k)`` with ``H = L L^T``.
    """
    rhs = [neg(r) for r in rd]
    for k, c in enumerate(cones):
        wv = _w_apply(scs[k], v[k], inverse=True)
        t = [add(a, b_) for a, b_ in zip(_w_inv2(scs[k], [neg(r) for r in rp[k]]), wv, strict=True)]
        ct = _ct(c, t)
        for j, i in enumerate(c.cols):
            rhs[i] = add(rhs[i], select(on[k], ct[j], 0.0))
    dx = _cho_solve(L, rhs)
    dzs, dss = [], []
    for k, c in enumerate(cones):
        ds = [add(r, d) for r, d in zip(rp[k], _cx(c, dx), strict=True)]
        wv = _w_apply(scs[k], v[k], inverse=True)
        dz = [sub(a, b_) for a, b_ in zip(wv, _w_inv2(scs[k], ds), strict=True)]
        dzs.append(_on3(on[k], dz, [0.0] * 3))
        dss.append(_on3(on[k], ds, [0.0] * 3))
    return dx, dss, dzs


def _inv_step(on, s, z, dss, dzs) -> Scalar:
    """``1 / (largest step keeping every active cone's s and z inside)``."""
    T: Scalar = 0.0
    for k in range(len(on)):
        tk = _max(_inv_max_step(s[k], dss[k]), _inv_max_step(z[k], dzs[k]))
        T = _max(T, select(on[k], tk, 0.0))
    return T


def cone_rows(normal: Sequence[Scalar], mu: Scalar) -> list[list[Scalar]]:
    """Cone coordinates of a force in the friction cone of an outward normal.

    Args:
        normal: outward surface normal ``n`` (3 scalars, any length > 0; normalised here).
        mu: friction coefficient (> 0): the cone's half-angle is ``atan(mu)``.

    Returns:
        3 rows of 3 scalars ``C`` with ``C f = (mu (-n . f), t1 . f, t2 . f)`` (``t1, t2``
        an orthonormal basis of the tangent plane): ``C f in Q^3`` iff ``f`` pushes into the
        surface within the cone.
    """
    n2 = sum_([mul(v, v) for v in normal])
    inv = div(1.0, sqrt(n2))
    nx, ny, nz = (mul(v, inv) for v in normal)
    # tangent basis without branches (Duff et al., "Building an orthonormal basis, revisited",
    # JCGT 2017)
    sgn = select(gt(0.0, nz), -1.0, 1.0)
    a = div(-1.0, add(sgn, nz))
    bxy = mul(mul(nx, ny), a)
    t1 = (add(1.0, mul(mul(sgn, mul(nx, nx)), a)), mul(sgn, bxy), neg(mul(sgn, nx)))
    t2 = (bxy, add(sgn, mul(mul(ny, ny), a)), neg(ny))
    return [[neg(mul(mu, nx)), neg(mul(mu, ny)), neg(mul(mu, nz))], list(t1), list(t2)]


def solve_cones(
    A: Sequence[Sequence[Scalar]],
    b: Sequence[Scalar],
    cones: Sequence[Cone],
    x0: Sequence[Scalar],
    eps: float,
    iterations: int,
    tol: float,
) -> ConeSolution:
    """Minimise ``1/2 |A x - b|^2 + eps/2 |x|^2`` with every cone ``C_k x[cols_k] in Q^3``.

    Primal-dual interior-point method with Mehrotra's predictor-corrector and Nesterov-Todd
    scaling, ``iterations`` steps (see the module docstring). Cones whose ``on`` mask is false in
    a frame are left out of that frame's problem.

    Args:
        A: ``R`` rows of ``u`` scalars.
        b: ``R`` scalars.
        cones: the constraints.
        x0: ``u`` scalars, the starting point (any; e.g. the pseudo-inverse solution).
        eps: regularisation (> 0).
        iterations: the fixed iteration budget.
        tol: convergence tolerance (relative residuals and duality gap).

    Returns:
        :class:`ConeSolution`.
    """
    R, u = len(b), len(x0)
    # ---- the problem: P = A^T A + eps I, q = -A^T b (formed once per frame)
    P = [[sum_([mul(A[r][i], A[r][j]) for r in range(R)]) for j in range(i + 1)]
         for i in range(u)]  # fmt: skip
    for i in range(u):
        P[i][i] = add(P[i][i], eps)
    q = [neg(sum_([mul(A[r][i], b[r]) for r in range(R)])) for i in range(u)]
    qq = _dot(q, q)
    on = [c.on for c in cones]
    m_on = sum_([select(o, 1.0, 0.0) for o in on])
    inv_m = div(1.0, _max(m_on, 1.0))
    # C_k^T J C_k: constant part of each cone's block of the Newton matrix
    CJC = [[[_jdot([row[i] for row in c.C], [row[j] for row in c.C]) for j in range(len(c.cols))]
            for i in range(len(c.cols))] for c in cones]  # fmt: skip

    def Pmul(x: Sequence[Scalar]) -> list[Scalar]:  # noqa: N802
        return [sum_([mul(P[max(i, j)][min(i, j)], x[j]) for j in range(u)]) for i in range(u)]

    e = [1.0, 0.0, 0.0]
    # ---- starting point: x0; slacks C x0 moved inside the cones; duals at the cones' centres
    x = list(x0)
    st = [_cx(c, x) for c in cones]
    scale = add(1.0, sqrt(sum_([select(o, _dot(v, v), 0.0) for o, v in zip(on, st, strict=True)])))
    margin = mul(0.1, scale)
    inside0: Scalar = True
    for o, v in zip(on, st, strict=True):
        ok0 = logical_or(logical_not(o), logical_not(gt(0.0, _eig_min(v))))
        inside0 = logical_and(inside0, ok0)
    s, z = [], []
    for o, v in zip(on, st, strict=True):
        shift = _max(sub(margin, _eig_min(v)), 0.0)
        s.append(_on3(o, [add(v[0], shift), v[1], v[2]], e))
        z.append(_on3(o, [scale, 0.0, 0.0], e))

    done: Scalar = False
    frozen: Scalar = False
    it_done: Scalar = float(iterations)
    gap_tol = mul(tol, add(1.0, qq))
    freeze_gap = mul(FREEZE_GAP, add(1.0, qq))
    floor = eps * 1e-6
    for it in range(iterations):
        # ---- residuals of the KKT conditions P x + q - C^T z = 0, C x - s = 0
        Px = Pmul(x)
        rd = [add(Px[i], q[i]) for i in range(u)]
        rp = []
        for k, c in enumerate(cones):
            ctz = _ct(c, z[k])
            for j, i in enumerate(c.cols):
                rd[i] = sub(rd[i], select(on[k], ctz[j], 0.0))
            rp.append(
                [select(on[k], sub(a, b_), 0.0) for a, b_ in zip(_cx(c, x), s[k], strict=True)]
            )
        # ---- Nesterov-Todd scaling and the Newton matrix H = P + sum C^T W^-2 C
        scs = [_nt_scaling(s[k], z[k]) for k in range(len(cones))]
        lam = [_w_apply(scs[k], z[k], inverse=False) for k in range(len(cones))]
        H = [list(row) for row in P]
        for k, c in enumerate(cones):
            wh = [scs[k].w[0], neg(scs[k].w[1]), neg(scs[k].w[2])]
            g = _ct(c, wh)
            inv_eta2 = div(1.0, mul(scs[k].eta, scs[k].eta))
            for a, i in enumerate(c.cols):
                for bb, j in enumerate(c.cols):
                    if j > i:
                        continue
                    blk = mul(inv_eta2, sub(mul(2.0, mul(g[a], g[bb])), CJC[k][a][bb]))
                    H[i][j] = add(H[i][j], select(on[k], blk, 0.0))
        Hs = [[H[max(i, j)][min(i, j)] for j in range(u)] for i in range(u)]
        L = _cholesky(Hs, floor)

        # ---- predictor (affine scaling): lam o (W dz + W^-1 ds) = -lam o lam
        dx_a, ds_a, dz_a = _newton(cones, on, L, rd, rp, scs, [[neg(v) for v in lk] for lk in lam])
        T_a = _inv_step(on, s, z, ds_a, dz_a)
        alpha_a = select(gt(T_a, 1.0), div(1.0, _max(T_a, 1.0)), 1.0)
        mu = mul(sum_([select(on[k], _dot(s[k], z[k]), 0.0) for k in range(len(cones))]), inv_m)
        one_minus = sub(1.0, alpha_a)
        sigma = mul(mul(one_minus, one_minus), one_minus)
        # ---- corrector: lam o lam + (W^-1 ds_a) o (W dz_a) - sigma mu e (Mehrotra), and the same
        # without the second-order term; the step that lowers the gap more is taken (Mehrotra's
        # term alone can cycle when the predictor is poor, e.g. forces at the cones' apexes)
        steps = []
        for second_order in (True, False):
            vs = []
            for k in range(len(cones)):
                ll = _jordan(lam[k], lam[k])
                dsk = [sub(ll[0], mul(sigma, mu)), ll[1], ll[2]]
                if second_order:
                    corr = _jordan(_w_apply(scs[k], ds_a[k], inverse=True),
                                   _w_apply(scs[k], dz_a[k], inverse=False))  # fmt: skip
                    dsk = [add(a, c_) for a, c_ in zip(dsk, corr, strict=True)]
                vs.append(_jordan_solve(lam[k], [neg(v) for v in dsk]))
            dx, ds, dz = _newton(cones, on, L, rd, rp, scs, vs)
            T = _inv_step(on, s, z, ds, dz)
            alpha = select(gt(T, 0.99), div(0.99, _max(T, 0.99)), 1.0)
            s_new = [[add(a, mul(alpha, d)) for a, d in zip(s[k], ds[k], strict=True)]
                     for k in range(len(cones))]  # fmt: skip
            z_new = [[add(a, mul(alpha, d)) for a, d in zip(z[k], dz[k], strict=True)]
                     for k in range(len(cones))]  # fmt: skip
            gap = sum_([select(on[k], _dot(s_new[k], z_new[k]), 0.0) for k in range(len(cones))])
            x_new = [add(xi, mul(alpha, di)) for xi, di in zip(x, dx, strict=True)]
            steps.append((x_new, s_new, z_new, gap))
        plain = gt(steps[0][3], steps[1][3])
        x_new, s_new, z_new = (
            [select(plain, b_, a) for a, b_ in zip(steps[0][0], steps[1][0], strict=True)],
            [[select(plain, b_, a) for a, b_ in zip(u1, u2, strict=True)]
             for u1, u2 in zip(steps[0][1], steps[1][1], strict=True)],
            [[select(plain, b_, a) for a, b_ in zip(u1, u2, strict=True)]
             for u1, u2 in zip(steps[0][2], steps[1][2], strict=True)],
        )  # fmt: skip
        # ---- take the step unless it went non-finite
        ok = isfinite(sum_([*x_new, *(v for sk in s_new for v in sk),
                            *(v for zk in z_new for v in zk)]))  # fmt: skip
        keep = logical_or(frozen, logical_not(ok))
        x = [select(keep, a, b_) for a, b_ in zip(x, x_new, strict=True)]
        s = [[select(keep, a, b_) for a, b_ in zip(s[k], s_new[k], strict=True)]
             for k in range(len(cones))]  # fmt: skip
        z = [[select(keep, a, b_) for a, b_ in zip(z[k], z_new[k], strict=True)]
             for k in range(len(cones))]  # fmt: skip
        # iterations: the first at which the duality gap met tol (a cheap per-step test; the
        # residuals are checked once, at the end)
        gap = sum_([select(on[k], _dot(s[k], z[k]), 0.0) for k in range(len(cones))])
        newly = logical_and(logical_not(gt(gap, gap_tol)), logical_not(done))
        it_done = select(newly, float(it + 1), it_done)
        done = logical_or(done, newly)
        # stop far below the tolerance: later steps only stir rounding noise (W grows like
        # 1 / sqrt(gap)) and could spoil the residuals
        frozen = logical_not(gt(gap, freeze_gap))
    # active: the slack is on the cone's boundary (or apex) to within 10 tol of its size plus
    # one unit (N), so a slack at the apex (size ~0) counts; the dual alone cannot tell, as it
    # is only eps-sized when the cone merely picks a point of the least-squares set
    active = [logical_and(o, logical_not(gt(_eig_min(sk), mul(10.0 * tol, add(sk[0], 1.0)))))
              for o, sk in zip(on, s, strict=True)]  # fmt: skip
    # x0 inside every cone (e.g. the pseudo-inverse solution, the eps -> 0 limit of the
    # unconstrained problem): it is the answer. Returned exactly, since along null(A) the
    # iterate is pinned only by eps, i.e. to rounding / eps.
    conv = _converged(P, q, qq, cones, on, x, s, z, tol)
    return ConeSolution(
        [select(inside0, a, b_) for a, b_ in zip(x0, x, strict=True)],
        logical_or(inside0, conv),
        select(inside0, 0.0, it_done),
        [logical_and(logical_not(inside0), a) for a in active],
    )


def _converged(P, q, qq, cones, on, x, s, z, tol: float) -> Scalar:
    """Relative KKT residuals and duality gap below ``tol`` (squared norms, no square roots)."""
    u = len(x)
    rd = [add(sum_([mul(P[max(i, j)][min(i, j)], x[j]) for j in range(u)]), q[i])
          for i in range(u)]  # fmt: skip
    rp2: Scalar = 0.0
    ss: Scalar = 0.0
    gap: Scalar = 0.0
    for k, c in enumerate(cones):
        xs = [x[i] for i in c.cols]
        ctz = [sum_([mul(c.C[r][j], z[k][r]) for r in range(3)]) for j in range(len(c.cols))]
        for j, i in enumerate(c.cols):
            rd[i] = sub(rd[i], select(on[k], ctz[j], 0.0))
        r = [sub(_dot(row, xs), sv) for row, sv in zip(c.C, s[k], strict=True)]
        rp2 = add(rp2, select(on[k], _dot(r, r), 0.0))
        ss = add(ss, select(on[k], _dot(s[k], s[k]), 0.0))
        gap = add(gap, select(on[k], _dot(s[k], z[k]), 0.0))
    t2 = tol * tol
    ok_d = logical_not(gt(_dot(rd, rd), mul(t2, add(1.0, qq))))
    ok_p = logical_not(gt(rp2, mul(t2, add(1.0, ss))))
    ok_g = logical_not(gt(gap, mul(tol, add(1.0, qq))))
    return logical_and(logical_and(ok_d, ok_p), ok_g)


# ------------------------------------------------------------------------------- tensor wrapper


def cone_constrained_lstsq(
    A: Tensor,
    b: Tensor,
    cones: Sequence[tuple[Sequence[int], Tensor]],
    *,
    on: Tensor | None = None,
    x0: Tensor | None = None,
    settings: FrictionCones | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Batched :func:`solve_cones` on tensors (eager; for tests and experiments).

    Args:
        A: ``(*B, R, u)``.
        b: ``(*B, R)``.
        cones: per cone ``(cols, C)`` with ``C`` ``(*B, 3, len(cols))`` (or ``(3, len(cols))``).
        on: ``(*B, m)`` bool, which cones apply (default all).
        x0: ``(*B, u)`` starting point (default ``pinv(A) b``).
        settings: iteration budget, ``eps``, ``tol`` (default :class:`FrictionCones`).

    Returns:
        ``x (*B, u)``, ``converged (*B,)`` bool, ``iterations (*B,)`` int64, ``active (*B, m)``
        bool.

    Raises:
        InputError: inconsistent shapes.

    Example:
        >>> A = torch.tensor([[1.0, 1.0]], dtype=torch.float64)  # one equation, two unknowns
        >>> C = torch.tensor([[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]], dtype=torch.float64)
        >>> x, ok, it, act = cone_constrained_lstsq(A, torch.tensor([-2.0], dtype=A.dtype),
        ...                                         [((0, 1), C)])  # x0 >= 0
        >>> x.round(decimals=6), bool(ok), act.tolist()
        (tensor([ 0., -2.], dtype=torch.float64), True, [True])
    """
    if A.dim() < 2 or b.shape[-1] != A.shape[-2]:
        raise InputError(f"A must be (*B, R, u) and b (*B, R); got {tuple(A.shape)}, "
                         f"{tuple(b.shape)}")  # fmt: skip
    R, u = A.shape[-2:]
    batch = torch.broadcast_shapes(A.shape[:-2], b.shape[:-1])
    n = int(torch.Size(batch).numel())
    settings = settings or FrictionCones()
    iters, eps, tol = settings.resolved(A.dtype)
    Af = A.expand(*batch, R, u).reshape(n, R, u)
    bf = b.expand(*batch, R).reshape(n, R)
    if x0 is None:
        x0f = (torch.linalg.pinv(Af, rcond=1e-10) @ bf.unsqueeze(-1)).squeeze(-1)
    else:
        x0f = x0.expand(*batch, u).reshape(n, u)
    cs = []
    for k, (cols, C) in enumerate(cones):
        cols = tuple(int(c) for c in cols)
        if C.shape[-2:] != (3, len(cols)) or any(not 0 <= c < u for c in cols):
            raise InputError(f"cone {k}: C must be (*B, 3, {len(cols)}) over columns in [0, {u})")
        Cf = C.expand(*batch, 3, len(cols)).reshape(n, 3, len(cols))
        o = True if on is None else on.expand(*batch, len(cones)).reshape(n, -1)[:, k]
        cs.append(Cone(cols, [[Cf[:, r, j] for j in range(len(cols))] for r in range(3)], o))
    sol = solve_cones([[Af[:, r, j] for j in range(u)] for r in range(R)],
                      [bf[:, r] for r in range(R)], cs, [x0f[:, j] for j in range(u)], eps,
                      iters, tol)  # fmt: skip

    def t(v: Scalar, dtype=A.dtype) -> Tensor:
        return v.to(dtype) if isinstance(v, Tensor) else torch.full((n,), v, dtype=dtype)

    x = torch.stack([t(v) for v in sol.x], -1).reshape(*batch, u)
    act = (torch.stack([t(v, torch.bool) for v in sol.active], -1) if cones
           else torch.zeros(n, 0, dtype=torch.bool))  # fmt: skip
    return (x, t(sol.converged, torch.bool).reshape(batch),
            t(sol.iterations).round().to(torch.int64).reshape(batch),
            act.reshape(*batch, len(cones)))  # fmt: skip
