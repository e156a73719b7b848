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
positive definite) and solves it for the predictor and the corrector right sides (the MAP
objective: one solve, see Objectives). Why this, for
batched small problems (``u`` = 3 to 18 unknowns, 1 to 6 cones, millions of frames):

* **Accuracy at a fixed budget, from a cold start.** The iteration count of an interior-point
  method hardly depends on the data: 10 to 20 iterations reach rounding level on these
  problems whatever their conditioning. First-order methods (ADMM on the same normal equations,
  projected gradient) converge linearly at a rate set by the conditioning of ``A`` and the angle
  between the cones and ``null(A)``; the estimator's matrices are rank-deficient by design
  (that is why the cones are needed), and ADMM typically needs hundreds of iterations for 1e-6
  here. A fixed budget is what makes the program exportable (straight-line code in ONNX) and one
  instruction stream for every frame on SIMD lanes or CUDA threads, so the method whose budget
  can be small and data-independent wins.
* **Cost.** The iterations are one :func:`torchcontact._scalar.loop`: a generated kernel holds
  the code of one iteration and leaves the loop once every frame of its vector block has stopped
  (a frame stops when its iterate no longer moves, see below), so the cost follows the frames'
  own iteration counts (held-out iCub frames with one to four contacts, ``benchmarks/cones.py``:
  the MAP objective 7.8 per solved frame and 8.2 per block of four, min-norm 12.4 per solved
  frame), not the budget. Square cones (a force's friction cone) are solved in cone coordinates
  ``y = C_k x`` (``A C_k^-1`` formed once per frame), where ``C_k = I`` and the iterations skip
  every product with it. One ``u x u`` Cholesky per iteration (about ``u^3 / 6`` multiply-adds:
  288 for four pure forces): a Woodbury (capacitance) form through the ``R x R`` matrix
  ``I + A D^-1 A^T`` costs more for ``u <= 2 R`` (12 unknowns, 6 rows: ~1000 operations against
  ~690) and about the same for ``u = 18``, so the dense form stays.
* **Branch-free.** Step lengths to the cone boundaries have closed forms; every choice is a
  ``select``; a step that would make the iterate non-finite is not taken. The first round also
  tried the step without Mehrotra's second-order term each iteration and kept the better one
  (against cycling at the cones' apexes); on every test problem, apex solutions included, the
  Mehrotra step alone converged in as many iterations to the same accuracy against clarabel,
  and it saves a third of the Newton solves.

**When a frame stops.** Along ``null(A)`` only ``eps`` pins the solution, so a duality gap that
meets a usual tolerance (1e-6 relative) leaves the forces far from the regularised optimum
(measured: tens of percent on the iCub's rank-deficient problems). A frame therefore iterates
until its gap is below :data:`STOP_GAP` (1e-16 of ``1 + |A^T b|^2`` in float64; the force then
agrees with 40-iteration runs to ~1e-4 relative), or below :data:`STALL_GAP` after a step that
did not halve it (the gap's rounding floor, reached on infeasible problems); from then on its
iterate does not move.

**Warm start.** The iterations start at ``x_start`` (the previous frame's estimate) or at the
pseudo-inverse solution ``x_pinv``. When ``x_pinv`` lies inside every cone it is the answer,
returned as it is: it is the ``eps -> 0`` limit of the unconstrained problem, which the
iterates approach only to rounding / ``eps`` along ``null(A)``. The slacks start at ``C_k x0``
moved inside the cones and the duals at a multiple of the cone's centre, as interior-point
methods require (the dual of the previous frame is not reused: a point on the cone boundary is
a poor start).

**Starting point of the MAP objective.** Its iterations end on the central path at ``nu``, not at
complementarity 0, so its duals start on the central path's complementarity, ``z = mu0 s^-1``
(``s o z = mu0 e``, ``s^-1 = J s / (s^T J s)``). Cold, ``mu0 = scale sqrt(nu)``: the geometric
mean of the target ``nu`` and the ``scale^2`` of duals at the cones' centre (the min-norm start,
which begins ~1e6 times above ``nu`` on the iCub and spends about 5 iterations coming down).
Starting at ``nu`` itself is faster on the iCub (5.1 iterations) but leaves a frame whose
pseudo-inverse estimate lies far outside its cone crawling (``z`` must grow by orders of
magnitude while ``s`` may move only 99 % of the way to the boundary per step: on random tcarm
readings a frame did not converge in 25 iterations; from ``scale sqrt(nu)`` it takes 16).
Warm, ``mu0 = nu``: the previous frame's estimate with the duals its own optimality gives
(slacks :data:`WARM_MARGIN` inside the cones). Measured (``docs/accuracy.md``): held-out iCub
frames, 7.8 iterations per solved frame against 10.5 before, at most 13 against 17, the answers
equal to 5e-7 N; a smooth simulated tcarm log, 4.4 warm-started and 8.2 cold (7.0 and 10.7
before; 8.6 warm-started with the min-norm start's duals). From an unrelated predecessor the
warm start is poor (a start at ``nu`` far from the answer crawls as above) and the frame restarts
cold: warm-start consecutive frames only (as :class:`PreviousFrame` and the log pipeline do).

**Status per frame.** ``iterations`` (the iterations the frame ran until it stopped; the budget
if it never did; 0 when the pseudo-inverse solution was the answer), ``converged`` (it stopped
and its relative KKT residuals meet ``tol``) and per cone ``active`` (the constraint binds: the
force is on the cone's boundary, or at its apex, to within ``10 tol`` relative). A frame that
did not converge keeps its last iterate (inside the cones) and gets status bit 256 of
:data:`torchcontact.STATUS` (a warning: it is not ok). A warm-started frame that does not
converge first starts again from the pseudo-inverse solution with a budget of its own, so that a
warm start changes the iterations a frame runs, never its answer (the issue that brought this in
measured 68 of 13,013 warm-started frames unconverged, up to 45 N off, all marked ok).

**Objectives** (:class:`FrictionCones`): the minimum-norm point above (``"min_norm"``), or the
maximum a posteriori estimate under :class:`ForcePrior` (``"map"``, the default in float64):
``1/2 |A x - b|^2 + (eps + 1/s^2)/2 |x|^2 - nu/2 sum_k log((C_k x)^T J (C_k x))``, the point
of the central path at ``nu`` (``s o z = nu e``), which the same iterations reach when each
step aims at ``nu + sigma (mu - nu)`` instead of ``sigma mu``. There a step is one solve, with
``sigma = 1 - alpha`` of the previous step's length ``alpha`` (after a full step straight at
``nu``): Mehrotra's second-order term was left out first (with it 3 % of multi-contact frames
stalled at step length ~0 near a cone's boundary), and then the predictor had no other use than
``sigma``; without it the weighted estimator's time on the iCub benchmark fell by 12 % (CPU
kernels, 20,000 frames: 66 to 59 ms) for about 5 % more iterations (7.8 against 7.4 per solved
frame; a fixed ``sigma`` of 0 stalls frames far outside their cones, 0.05 to 0.3 needs 9.7 to
20). A frame stops after a full step that leaves ``|s o z - nu
e|`` at rounding level. ``docs/accuracy.md`` compares the objectives on held-out data.

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

from torchcontact._internal import counts
from torchcontact._scalar import (
    Scalar,
    add,
    div,
    gt,
    is_const,
    isfinite,
    logical_and,
    logical_not,
    logical_or,
    loop,
    mul,
    neg,
    select,
    sqrt,
    sub,
    sum_,
)
from torchcontact.errors import InputError
from torchcontact.solve import cho_solve, cholesky

__all__ = [
    "DEFAULT_EPS",
    "DEFAULT_TOL",
    "STALL_GAP",
    "STOP_GAP",
    "WARM_MARGIN",
    "Cone",
    "ConeSolution",
    "OBJECTIVES",
    "ForcePrior",
    "FrictionCones",
    "PreviousFrame",
    "cone_constrained_lstsq",
    "cone_rows",
    "solve_cones",
]

#: Objectives of :class:`FrictionCones`.
OBJECTIVES = ("map", "min_norm")
#: Default regularisation ``eps`` per dtype (``A`` has entries of order 1 and metres).
DEFAULT_EPS: dict[torch.dtype, float] = {torch.float64: 1e-9, torch.float32: 1e-5}
#: A frame stops moving once its duality gap is below this, relative to ``1 + |A^T b|^2``.
#: A frame stops (its iterate no longer moves) once its duality gap is below this, relative to
#: ``1 + |A^T b|^2``, per dtype: along ``null(A)`` only ``eps`` pins the solution, so the gap must
#: fall far below ``eps |x|^2`` before the iterate settles there (measured: the force moves by
#: ~sqrt(gap) relative on the iCub's rank-deficient problems).
STOP_GAP: dict[torch.dtype, float] = {torch.float64: 1e-16, torch.float32: 1e-11}
#: ... or once a step lowers a gap below this (relative likewise) by less than half: the gap has
#: reached its rounding floor (measured: 1e-16 to 1e-15 on infeasible problems in float64).
STALL_GAP: dict[torch.dtype, float] = {torch.float64: 1e-14, torch.float32: 1e-8}
#: Slacks of a warm start are moved inside the cones by the first of these times the scale
#: ``1 + |C x0|``, its duals start at the second times the scale (cold: 0.1 and 1; the MAP
#: objective's duals start at ``nu s^-1`` warm, see the module docstring): a warm start is taken
#: to be near the solution. Measured: on a simulated tcarm log (smooth motion, contacts
#: held 0.3 to 3 s), from each frame's predecessor, 7.3 iterations on average against 11.4 cold;
#: from an unrelated frame's estimate (iCub, four contacts) 14.1 against 12.7.
WARM_MARGIN = (1e-3, 1e-2)
#: Default convergence tolerance per dtype (relative KKT residuals of a stopped frame).
DEFAULT_TOL: dict[torch.dtype, float] = {torch.float64: 1e-6, torch.float32: 1e-3}


@dataclass(frozen=True)
class ForcePrior:
    """The prior of the maximum a posteriori estimate inside the cones (``FrictionCones.prior``).

    Per pushing slot, a density on its force ``f`` (cone coordinates ``(t, y) = C f``, ``t = mu
    (-n . f)`` along the inward normal, ``y`` the tangential part):

    .. code-block:: text

        p(f)  ~  (t^2 - |y|^2)^(nu / 2)  exp(-|f|^2 / (2 s^2))     inside the cone, 0 outside

    The first factor vanishes on the cone's boundary and at its apex: it favours forces that
    push well inside the cone and are not vanishingly small (along the cone's axis the
    magnitude's density is ``~ |f|^nu exp(-|f|^2 / 2 s^2)``, largest at ``|f| = sqrt(nu) s``);
    the second bounds the magnitudes softly. With the Gaussian likelihood of the (weighted)
    readings the estimate minimises ``1/2 |A x - b|^2_Sigma^-1 + |x|^2 / (2 s^2) - nu/2 sum_k
    log(t_k^2 - |y_k|^2)``: a convex problem, the point of the interior-point method's central
    path at ``nu``, solved by the same iterations.

    Attributes:
        nu: exponent of the cone factor (> 0). 0.25 was chosen on four held-out distributions
            (``docs/accuracy.md``: magnitudes uniform in [2, 20] N and log-uniform in [0.5, 50]
            N, directions uniform in the cone and near its rim), where it beat the minimum-norm
            objective on all four; 1 won on the first only.
        scale: ``s`` in N; None (the default) sets it per frame and region from the data:
            ``s = relative |x_pinv| / sqrt(m)``, ``x_pinv`` the pseudo-inverse estimate and
            ``m`` the number of pushing slots (an empirical-Bayes choice that makes the estimate
            scale-equivariant: forces ten times larger give an estimate ten times larger).
        relative: the factor of the data-driven scale.
        unweighted_sigma: without a noise covariance (the paper's unit weights) the readings'
            noise is unknown; the likelihood then takes this standard deviation for every row
            (N, N m). Too large a value lets the prior pull observable forces (a single contact)
            away from the data; the default (0.01) keeps that pull below the F/T noise of
            common sensors.

    Example:
        >>> ForcePrior().nu
        0.25
    """

    nu: float = 0.25
    scale: float | None = None
    relative: float = 1.0
    unweighted_sigma: float = 0.01

    def __post_init__(self) -> None:
        for name in ("nu", "relative", "unweighted_sigma"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < float(v) < float("inf")):
                raise InputError(f"ForcePrior.{name} must be a finite number > 0, got {v!r}")
        if self.scale is not None and not (0 < float(self.scale) < float("inf")):
            raise InputError(f"ForcePrior.scale must be None or a finite number > 0 (N), got"
                             f" {self.scale!r}")  # fmt: skip

    def flags(self) -> tuple[float, float | None, float, float]:
        """``(nu, scale, relative, unweighted_sigma)`` as plain floats (a program's key)."""
        return (float(self.nu), None if self.scale is None else float(self.scale),
                float(self.relative), float(self.unweighted_sigma))  # fmt: skip


@dataclass(frozen=True)
class FrictionCones:
    """Settings of the friction-cone constrained estimate (``estimate(..., constraints=...)``).

    The cones themselves (normals, friction coefficients, which slots push) are per slot in
    :class:`~torchcontact.Contacts`.

    Attributes:
        iterations: interior-point iteration budget (the exported graph runs all of it;
            kernels and eager torch stop when every frame has stopped). Measured on held-out
            iCub frames with one to four contacts in float64: the MAP objective's frames stop
            after at most 13 iterations (7.8 on average), the min-norm objective's after at
            most 23 (12.4); with four contacts in float32 (min-norm) 7 to 16 (10). With the
            MAP objective a frame still going at :data:`RESTART_AT` restarts once with this
            budget again (``iterations + RESTART_AT`` in all, when ``iterations`` exceeds it).
        eps: regularisation ``eps`` of ``|A x - b|^2 + eps |x|^2`` (default
            :data:`DEFAULT_EPS` of the model's dtype).
        tol: tolerance of the ``converged`` flag on a stopped frame's relative KKT residuals
            (default :data:`DEFAULT_TOL`).
        objective: which point of the feasible set is the estimate (:data:`OBJECTIVES`):

            * ``"map"``: the maximum a posteriori estimate under :attr:`prior`, with the
              readings' noise from ``ft_covariance`` (or ``prior.unweighted_sigma`` without
              one). Assumes forces that push well inside their cones with magnitudes of the
              order the data suggest; it is interior to every cone (a force exactly on a cone's
              boundary or at its apex is approached, not reached). Measured on held-out iCub
              frames (``benchmarks/cones.py``, ``docs/accuracy.md``): with three or four
              contacts, 2.2x lower median error than the pseudo-inverse, against 1.75x for
              ``"min_norm"``, and ahead of it on each of four force distributions.
            * ``"min_norm"``: ``min |A x - b|^2 + eps |x|^2``, the smallest force inside the
              cones among the best fits. Assumes nothing about the forces beyond the cones: it
              is exact where they pin the forces (forces on the cones' boundaries), and biased
              towards small forces where they do not.
            * None (default): ``"map"`` in float64, ``"min_norm"`` in float32
              (:meth:`objective_of`).
        prior: the :class:`ForcePrior` of ``"map"``.

    Example:
        >>> FrictionCones(iterations=30).iterations
        30
        >>> FrictionCones().objective_of(torch.float64)
        'map'
    """

    iterations: int = 25
    eps: float | None = None
    tol: float | None = None
    objective: str | None = None
    prior: ForcePrior = ForcePrior()

    def __post_init__(self) -> None:
        if self.objective is not None and self.objective not in OBJECTIVES:
            raise InputError(f"FrictionCones.objective must be one of {OBJECTIVES}, got"
                             f" {self.objective!r}")  # fmt: skip
        if not isinstance(self.prior, ForcePrior):
            raise InputError(f"FrictionCones.prior must be a ForcePrior, got"
                             f" {type(self.prior).__name__}")  # fmt: skip
        if not (isinstance(self.iterations, int) and 1 <= self.iterations <= 200):
            raise InputError(f"FrictionCones.iterations must be an int in [1, 200], got "
                             f"{self.iterations!r}")  # fmt: skip
        for name in ("eps", "tol"):
            v = getattr(self, name)
            if v is not None and not (float(v) > 0 and float(v) < 1):
                raise InputError(f"FrictionCones.{name} must be in (0, 1), got {v!r}")

    def resolved(self, dtype: torch.dtype) -> tuple[int, float, float, tuple[float, float]]:
        """``(iterations, eps, tol, stop)`` with the defaults of ``dtype`` filled in.

        ``stop``: :data:`STOP_GAP` and :data:`STALL_GAP` of ``dtype``.
        """
        eps = DEFAULT_EPS.get(dtype, 1e-9) if self.eps is None else float(self.eps)
        tol = DEFAULT_TOL.get(dtype, 1e-6) if self.tol is None else float(self.tol)
        stop = (STOP_GAP.get(dtype, 1e-16), STALL_GAP.get(dtype, 1e-14))
        return self.iterations, eps, tol, stop

    def program_flags(self, dtype: torch.dtype) -> tuple:
        """:meth:`resolved`, then the prior's :meth:`ForcePrior.flags` (None for min-norm).

        The ``cones`` flags of :func:`torchcontact.estimation.programs.estimate_program`.
        """
        prior = self.prior.flags() if self.objective_of(dtype) == "map" else None
        return (*self.resolved(dtype), prior)

    def objective_of(self, dtype: torch.dtype) -> str:
        """The objective used in ``dtype``.

        ``objective``, or by default ``"map"`` in float64 and ``"min_norm"`` in float32 (the
        posterior's curvature along ``null(A)`` is ~1e-6 of the readings' on the iCub, below
        what float32 iterations resolve).
        """
        if self.objective is not None:
            return self.objective
        return "map" if dtype == torch.float64 else "min_norm"


@dataclass(frozen=True)
class PreviousFrame:
    """Warm start every frame from its predecessor's estimate (``estimate(..., warm_start=...)``).

    The batch is a time series (frames in order along the flattened batch). Its frames are
    estimated in waves: a batch of ``n`` frames is cut into blocks of ``S = ceil(n / wave)``
    consecutive frames, and wave ``j`` holds the ``j``-th frame of every block (about ``wave``
    frames, one batched call), started from wave ``j - 1``'s estimates. The first frame of each
    block starts cold (the pseudo-inverse solution), but the batch's first one, which starts
    from ``before``. A warm start changes the iterations a frame needs (:data:`WARM_MARGIN`), not
    its answer (to the solver's accuracy).

    Attributes:
        before: ``(force, moment)``, each ``(K, 3)``, the estimate of the frame before the batch
            (link frames; NaN rows start cold), or None.
        wave: frames per batched call (>= 1); smaller waves warm-start more frames (all but one
            in ``S``) at the price of more calls.

    Example:
        >>> PreviousFrame(wave=512).wave
        512
    """

    before: tuple[Tensor, Tensor] | None = None
    wave: int = 1024

    def __post_init__(self) -> None:
        if not (isinstance(self.wave, int) and self.wave >= 1):
            raise InputError(f"PreviousFrame.wave must be an int >= 1, got {self.wave!r}")


class Cone(NamedTuple):
    """One second-order cone constraint ``C x[cols] in Q^3`` of :func:`solve_cones`.

    Attributes:
        cols: indices of the unknowns it reads (one slot's).
        C: 3 rows of ``len(cols)`` scalars: the cone coordinates ``(t, y1, y2)`` of the slot
            (invertible when square, as a friction cone's is).
        on: mask scalar: the constraint applies in this frame (else it is ignored).
    """

    cols: tuple[int, ...]
    C: list[list[Scalar]]
    on: Scalar


class ConeSolution(NamedTuple):
    """Result of :func:`solve_cones` (scalars).

    Attributes:
        x: ``u`` unknowns.
        converged: mask: the frame stopped within the budget and its residuals met ``tol``.
        iterations: the iterations the frame ran until it stopped (the budget if it never did,
            0 when the pseudo-inverse solution is the answer), as a float.
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


# ------------------------------------------------------------------ second-order cone algebra
# A cone vector is (v0, v1, v2): v0 the axis, (v1, v2) the disc. J = diag(1, -1, -1).


def _jdot(a: Sequence[Scalar], b: Sequence[Scalar]) -> Scalar:
    """``a^T J b``."""
    return sub(mul(a[0], b[0]), add(mul(a[1], b[1]), mul(a[2], b[2])))


def _eig_min(v: Sequence[Scalar]) -> Scalar:
    """Smallest Jordan eigenvalue ``v0 - |v1|`` (>= 0 inside the cone)."""
    return sub(v[0], sqrt(add(mul(v[1], v[1]), mul(v[2], v[2]))))


class _Scaling(NamedTuple):
    """Nesterov-Todd scaling ``W = eta Wbar(w)`` of one cone (``W z = W^{-1} s = lam``).

    With the reciprocals the products need (computed once per iteration and cone).
    """

    eta: Scalar
    w: list[Scalar]  # w^T J w = 1, w0 > 0
    inv_eta: Scalar  # 1 / eta
    inv_eta2: Scalar  # 1 / eta^2
    inv_1w0: Scalar  # 1 / (1 + w0)


def _nt_scaling(s: Sequence[Scalar], z: Sequence[Scalar]) -> _Scaling:
    ns = sqrt(_jdot(s, s))
    nz = sqrt(_jdot(z, z))
    inv_ns, inv_nz = div(1.0, ns), div(1.0, nz)
    sb = [mul(v, inv_ns) for v in s]  # the same products as _inv_max_step's
    zb = [mul(v, inv_nz) for v in z]
    gamma = sqrt(mul(add(1.0, _dot(sb, zb)), 0.5))
    inv2g = div(0.5, gamma)
    w = [mul(add(sb[0], zb[0]), inv2g), mul(sub(sb[1], zb[1]), inv2g),
         mul(sub(sb[2], zb[2]), inv2g)]  # fmt: skip
    eta = sqrt(mul(ns, inv_nz))
    return _Scaling(eta, w, div(1.0, eta), mul(nz, inv_ns), div(1.0, add(1.0, w[0])))


def _w_apply(sc: _Scaling, v: Sequence[Scalar], inverse: bool) -> list[Scalar]:
    """``W v`` (or ``W^{-1} v``): ``Wbar = [[w0, w1^T], [w1, I + w1 w1^T / (1 + w0)]]``."""
    w = sc.w
    w1v1 = add(mul(w[1], v[1]), mul(w[2], v[2]))
    if inverse:  # Wbar^{-1} = J Wbar J
        first = sub(mul(w[0], v[0]), w1v1)
        coef = sub(mul(w1v1, sc.inv_1w0), v[0])
        scale = sc.inv_eta
    else:
        first = add(mul(w[0], v[0]), w1v1)
        coef = add(mul(w1v1, sc.inv_1w0), v[0])
        scale = sc.eta
    out = [first, add(v[1], mul(coef, w[1])), add(v[2], mul(coef, w[2]))]
    return [mul(scale, x) for x in out]


def _w_inv2(sc: _Scaling, v: Sequence[Scalar]) -> list[Scalar]:
    """``W^{-2} v = eta^{-2} (2 wh wh^T - J) v`` with ``wh = J w``."""
    wh = (sc.w[0], neg(sc.w[1]), neg(sc.w[2]))
    t = mul(2.0, _dot(wh, v))
    inv = sc.inv_eta2
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
    c = mul(add(d[0], r0), div(1.0, add(1.0, xb[0])))  # the reciprocal is shared by all d
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
    dx = cho_solve(L, rhs)
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


class _Problem(NamedTuple):
    """The per-frame constants of one constrained solve (formed once, before the iterations)."""

    P: list[list[Scalar]]  # lower triangle of A^T A + eps I
    q: list[Scalar]  # -A^T b
    cones: Sequence[Cone]
    on: list[Scalar]
    CJC: list  # per cone, C^T J C (lower triangle)
    inv_m: Scalar  # 1 / (number of cones that apply)
    floor: float  # smallest pivot of the Newton matrix's Cholesky factor
    nu: Scalar  # the barrier weight: the iterates go to the point of the central path s o z = nu e


#: The previous step length a centred solve's first iteration assumes (its centring ``sigma = 1 -
#: alpha``: halfway from ``mu`` to ``nu``).
ALPHA0 = 0.5

#: The MAP objective: a frame still going after this many iterations from its start restarts once
#: from the duals at the cones' centres (the min-norm start), with a budget of its own. From
#: the central path's complementarity a frame whose estimate lies far outside a cone crawls (its
#: duals must grow by orders of magnitude): on random iCub readings (500 frames, two force
#: contacts, 5 N per axis) 260 frames did not converge in 25 iterations from there, 0 with this
#: restart; on the held-out iCub frames every frame stops by iteration 13, before it.
RESTART_AT = 15


def _step(pb: _Problem, x: list[Scalar], s: list[list[Scalar]], z: list[list[Scalar]],
          alpha_prev: Scalar = ALPHA0):  # fmt: skip
    """One interior-point step from ``(x, s, z)``: the next iterate and its length.

    With ``nu = 0`` a Mehrotra predictor-corrector step (two solves of one factorization). With
    ``nu > 0`` the complementarity target is ``s o z = nu e`` instead of 0 and the step is one
    solve aiming at ``nu + sigma (mu - nu)`` with ``sigma = 1 - alpha_prev`` (the previous step's
    length: after a full step straight at ``nu``, after a short one closer to the current
    ``mu``), so that the point of the central path at ``nu`` is a fixed point of the step. The
    predictor's only use there was ``sigma`` (module docstring, Objectives).
    """
    cones, on, u = pb.cones, pb.on, len(x)
    # ---- residuals of the KKT conditions P x + q - C^T z = 0, C x - s = 0
    rd = [add(sum_([mul(pb.P[max(i, j)][min(i, j)], x[j]) for j in range(u)]), pb.q[i])
          for i in range(u)]  # fmt: skip
    rp = []
    for k, c in enumerate(cones):
        ctz = _ct(c, z[k])
        for j, i in enumerate(c.cols):
            rd[i] = sub(rd[i], select(on[k], ctz[j], 0.0))
        rp.append([select(on[k], sub(a, b_), 0.0) for a, b_ in zip(_cx(c, x), s[k], strict=True)])
    # ---- Nesterov-Todd scaling and the Newton matrix H = P + sum C^T W^-2 C
    scs = [_nt_scaling(s[k], z[k]) for k in range(len(cones))]
    lam = [_w_apply(scs[k], z[k], inverse=False) for k in range(len(cones))]
    H = [list(row) for row in pb.P]
    for k, c in enumerate(cones):
        wh = [scs[k].w[0], neg(scs[k].w[1]), neg(scs[k].w[2])]
        g = _ct(c, wh)
        inv_eta2 = scs[k].inv_eta2
        for a, i in enumerate(c.cols):
            for bb, j in enumerate(c.cols):
                if j > i:
                    continue
                blk = mul(inv_eta2, sub(mul(2.0, mul(g[a], g[bb])), pb.CJC[k][a][bb]))
                H[i][j] = add(H[i][j], select(on[k], blk, 0.0))
    L = cholesky([[H[max(i, j)][min(i, j)] for j in range(u)] for i in range(u)], pb.floor)
    nu = pb.nu
    centred = not (is_const(nu) and nu == 0)
    mu = mul(sum_([select(on[k], _dot(s[k], z[k]), 0.0) for k in range(len(cones))]), pb.inv_m)
    if centred:  # no predictor: the centring follows the previous step's length
        sigma = sub(1.0, alpha_prev)
    else:  # ---- predictor (affine scaling): lam o (W dz + W^-1 ds) = -lam o lam
        v_a = [[neg(v) for v in lk] for lk in lam]
        dx_a, ds_a, dz_a = _newton(cones, on, L, rd, rp, scs, v_a)
        T_a = _inv_step(on, s, z, ds_a, dz_a)
        alpha_a = select(gt(T_a, 1.0), div(1.0, _max(T_a, 1.0)), 1.0)
        one_minus = sub(1.0, alpha_a)
        sigma = mul(mul(one_minus, one_minus), one_minus)
    # ---- corrector (Mehrotra): lam o (W dz + W^-1 ds) = -(lam o lam + (W^-1 ds_a) o (W dz_a)
    # - sigma mu e), the same factorization; centred: the step itself
    vs = []
    for k in range(len(cones)):
        ll = _jordan(lam[k], lam[k])
        if not centred:
            corr = _jordan(_w_apply(scs[k], ds_a[k], inverse=True),
                           _w_apply(scs[k], dz_a[k], inverse=False))  # fmt: skip
            target = mul(sigma, mu)
        else:
            # towards the central path at nu: no second-order term, which stalls the step near
            # the cones' boundaries (measured: 3 % of the iCub's multi-contact frames stuck at
            # alpha ~ 0 with it, none without)
            target = add(nu, mul(sigma, sub(mu, nu)))
            corr = [0.0, 0.0, 0.0]
        rhs = [add(sub(ll[0], target), corr[0]), add(ll[1], corr[1]), add(ll[2], corr[2])]
        vs.append(_jordan_solve(lam[k], [neg(v) for v in rhs]))
    dx, ds, dz = _newton(cones, on, L, rd, rp, scs, vs)
    # ---- step: 0.99 of the way to the nearest cone boundary, at most a full step
    T = _inv_step(on, s, z, ds, dz)
    alpha = select(gt(T, 0.99), div(0.99, _max(T, 0.99)), 1.0)
    x_new = [add(xi, mul(alpha, di)) for xi, di in zip(x, dx, strict=True)]
    s_new = [[add(a, mul(alpha, d)) for a, d in zip(s[k], ds[k], strict=True)]
             for k in range(len(cones))]  # fmt: skip
    z_new = [[add(a, mul(alpha, d)) for a, d in zip(z[k], dz[k], strict=True)]
             for k in range(len(cones))]  # fmt: skip
    return x_new, s_new, z_new, alpha


_EYE3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def _inv3(C: Sequence[Sequence[Scalar]]) -> list[list[Scalar]]:
    """Inverse of a 3 x 3 matrix of scalars (adjugate over determinant)."""
    cof = [[sub(mul(C[(i + 1) % 3][(j + 1) % 3], C[(i + 2) % 3][(j + 2) % 3]),
                mul(C[(i + 1) % 3][(j + 2) % 3], C[(i + 2) % 3][(j + 1) % 3]))
            for j in range(3)] for i in range(3)]  # fmt: skip
    inv_det = div(1.0, _dot(C[0], cof[0]))
    return [[mul(cof[j][i], inv_det) for j in range(3)] for i in range(3)]


def _to_cone_coordinates(
    A: Sequence[Sequence[Scalar]], cones: Sequence[Cone], u: int
) -> tuple[list[list[Scalar]], list[Cone], list]:
    """``A T^-1``, the cones in the new coordinates, and per cone ``C^-1`` (None: not square)."""
    A2 = [list(row) for row in A]
    out, Cinv = [], []
    for c in cones:
        if len(c.cols) != 3:
            out.append(c)
            Cinv.append(None)
            continue
        ci = _inv3(c.C)
        for row, row2 in zip(A, A2, strict=True):
            for j, col in enumerate(c.cols):
                row2[col] = sum_([mul(row[c.cols[a]], ci[a][j]) for a in range(3)])
        out.append(Cone(c.cols, _EYE3, c.on))
        Cinv.append(ci)
    return A2, out, Cinv


def _apply_blocks(cones, C, Cinv, x: Sequence[Scalar], forward: bool) -> list[Scalar]:
    """``T x`` (``forward``, with the original ``C``) or ``T^-1 y`` on the square cones."""
    out = list(x)
    for k, (c, ci) in enumerate(zip(cones, Cinv, strict=True)):
        if ci is None:
            continue
        M = C[k] if forward else ci
        v = [x[i] for i in c.cols]
        for r, i in enumerate(c.cols):
            out[i] = _dot(M[r], v)
    return out


def solve_cones(
    A: Sequence[Sequence[Scalar]],
    b: Sequence[Scalar],
    cones: Sequence[Cone],
    x_pinv: Sequence[Scalar],
    eps: float,
    iterations: int,
    tol: float,
    stop: tuple[float, float] = (STOP_GAP[torch.float64], STALL_GAP[torch.float64]),
    x_start: Sequence[Scalar] | None = None,
    start_on: Scalar = True,
    nu: Scalar = 0.0,
    ridge: Scalar = 0.0,
    pinv_answer: Scalar = True,
) -> ConeSolution:
    """Minimise ``1/2 |A x - b|^2 + eps/2 |x|^2`` with every cone ``C_k x[cols_k] in Q^3``.

    With ``nu > 0`` (:class:`ForcePrior`) the objective is the negative log-posterior
    ``1/2 |A x - b|^2 + (eps + ridge)/2 |x|^2 - nu/2 sum_k log((C_k x)^T J (C_k x))``: the
    point of the interior-point method's central path at ``nu``, an interior point of every
    cone.

    Primal-dual interior-point method with Mehrotra's predictor-corrector and Nesterov-Todd
    scaling, at most ``iterations`` steps (see the module docstring). Cones whose ``on`` mask is
    false in a frame are left out of that frame's problem. The iterations are one
    :func:`torchcontact._scalar.loop`: a frame stops once its duality gap is below ``stop``
    (its iterate no longer moves), and a generated kernel leaves the loop once every frame of its
    block has.

    Args:
        A: ``R`` rows of ``u`` scalars.
        b: ``R`` scalars.
        cones: the constraints.
        x_pinv: ``u`` scalars, the pseudo-inverse solution ``pinv(A) b``: the answer when it lies
            inside every cone, else the start.
        eps: regularisation (> 0).
        iterations: the iteration budget.
        tol: convergence tolerance of a stopped frame's relative KKT residuals.
        stop: a frame stops when its duality gap is below ``stop[0] (1 + |A^T b|^2)``, or below
            ``stop[1] (1 + |A^T b|^2)`` after a step that did not halve it (:data:`STOP_GAP`,
            :data:`STALL_GAP`).
        x_start: ``u`` scalars, another starting point (e.g. the previous frame's estimate);
            None: ``x_pinv``.
        start_on: mask: the frame starts from ``x_start`` (else from ``x_pinv``), with the
            tighter start of a warm start (:data:`WARM_MARGIN`). A frame started there that
            does not converge within the budget restarts from ``x_pinv`` with a budget of its
            own: a warm start changes the iterations, never the answer.
        nu: barrier weight (>= 0; a constant or per-frame scalar).
        ridge: added to ``eps`` (per-frame scalar, >= 0): the Gaussian part of the prior.
        pinv_answer: mask: ``x_pinv`` inside every cone is the answer (the frame is not
            iterated). Always the case with ``nu = 0``; with a prior the caller passes "every
            unknown is observable", where the prior's pull is below the noise, and a frame
            without an active cone returns ``x_pinv`` too (the prior is one on pushing forces).

    Returns:
        :class:`ConeSolution`.
    """
    R, u, m = len(b), len(x_pinv), len(cones)
    # ---- cone coordinates: y = T x with T = C_k on the columns of each square cone (a friction
    # cone of a force), the identity elsewhere; then those cones read y directly (C = I), and
    # the iterations skip every product with C (constants fold them away)
    C = [c.C for c in cones]
    A, cones, Cinv = _to_cone_coordinates(A, cones, u)
    x_pinv = _apply_blocks(cones, C, Cinv, x_pinv, forward=True)
    if x_start is not None:
        x_start = _apply_blocks(cones, C, Cinv, x_start, forward=True)
    # ---- the problem: P = A^T A + eps T^-T T^-1, q = -A^T b (formed once per frame; A in
    # cone coordinates)
    P = [[sum_([mul(A[r][i], A[r][j]) for r in range(R)]) for j in range(i + 1)]
         for i in range(u)]  # fmt: skip
    eps_all = add(eps, ridge)
    reg: list[list[Scalar]] = [[eps_all if i == j else 0.0 for j in range(i + 1)]
                               for i in range(u)]  # fmt: skip
    for c, ci in zip(cones, Cinv, strict=True):
        if ci is not None:  # eps |T^-1 y|^2 on the cone's columns: eps Cinv^T Cinv
            for a, i in enumerate(c.cols):
                for bb, j in enumerate(c.cols[: a + 1]):
                    reg[i][j] = mul(eps_all, sum_([mul(ci[r][a], ci[r][bb]) for r in range(3)]))
    P = [[add(P[i][j], reg[i][j]) for j in range(i + 1)] for i in range(u)]
    q = [neg(sum_([mul(A[r][i], b[r]) for r in range(R)])) for i in range(u)]
    qq = _dot(q, q)
    on = [c.on for c in cones]
    m_on = sum_([select(o, 1.0, 0.0) for o in on])
    # C_k^T J C_k: constant part of each cone's block of the Newton matrix
    CJC = [[[_jdot([row[i] for row in c.C], [row[j] for row in c.C]) for j in range(len(c.cols))]
            for i in range(len(c.cols))] for c in cones]  # fmt: skip
    centred = not (is_const(nu) and nu == 0)
    pb = _Problem(P, q, cones, on, CJC, div(1.0, _max(m_on, 1.0)), eps * 1e-6, nu)
    # ---- the pseudo-inverse solution inside every cone (the eps -> 0 limit of the
    # unconstrained problem) is the answer: returned exactly, since along null(A) the iterates
    # are pinned only by eps, i.e. to rounding / eps
    # (with a prior: also a frame without any active cone, whose forces the prior does not cover)
    inside0: Scalar = True if not centred else logical_or(pinv_answer, logical_not(gt(m_on, 0.5)))
    for o, c in zip(on, cones, strict=True):
        ok0 = logical_or(logical_not(o), logical_not(gt(0.0, _eig_min(_cx(c, x_pinv)))))
        inside0 = logical_and(inside0, ok0)
    # ---- starting point: x0; slacks C x0 moved inside the cones; duals at the cones' centres
    e = [1.0, 0.0, 0.0]

    def start(x0: list[Scalar], warm: Scalar, centre: bool = False) -> list[Scalar]:
        st = [_cx(c, x0) for c in cones]
        size2 = sum_([select(o, _dot(v, v), 0.0) for o, v in zip(on, st, strict=True)])
        scale = add(1.0, sqrt(size2))
        margin = mul(select(warm, WARM_MARGIN[0], 0.1), scale)
        dual0 = mul(select(warm, WARM_MARGIN[1], 1.0), scale)
        # the MAP objective's duals (module docstring, "Starting point of the MAP objective"):
        # on the central path's complementarity at scale sqrt(nu) cold, at nu itself warm
        mu0 = select(warm, nu, mul(sqrt(nu), scale)) if centred else 0.0
        s0, z0 = [], []
        for o, v in zip(on, st, strict=True):
            shift = _max(sub(margin, _eig_min(v)), 0.0)
            sk = [add(v[0], shift), v[1], v[2]]
            s0.append(_on3(o, sk, e))
            if centred and not centre:  # s o z = mu0 e: z = mu0 s^-1, s^-1 = J s / (s^T J s)
                inv = div(mu0, _jdot(sk, sk))
                z0.append(_on3(o, [mul(inv, sk[0]), neg(mul(inv, sk[1])), neg(mul(inv, sk[2]))],
                               e))  # fmt: skip
            else:
                z0.append(_on3(o, [dual0, 0.0, 0.0], e))
        return [*x0, *(v for sk in s0 for v in sk), *(v for zk in z0 for v in zk)]

    gap_stop = mul(stop[0], add(1.0, qq))
    gap_stall = mul(stop[1], add(1.0, qq))
    if centred:  # |s o z - nu e|^2 summed over the cones, relative to nu^2 per cone
        nu2m = mul(mul(nu, nu), m_on)
        gap_stop = mul(100.0 * stop[0], nu2m)
        gap_stall = mul(100.0 * stop[1], nu2m)

    def unpack(state: Sequence[Scalar]) -> tuple[list, list, list, Scalar, Scalar, Scalar, Scalar]:
        # x, s, z, iterations, stopped, the previous gap and step length
        x = list(state[:u])
        s = [list(state[u + 3 * k : u + 3 * k + 3]) for k in range(m)]
        z = [list(state[u + 3 * m + 3 * k : u + 3 * m + 3 * k + 3]) for k in range(m)]
        return x, s, z, *state[u + 6 * m : u + 6 * m + 4]

    # the MAP objective's restart point (RESTART_AT), computed once before the loop
    centre0 = start(list(x_pinv), False, centre=True) if centred else None
    restart_base: list[Scalar] = [0.0]  # the count a loop starts from (read when it is traced)

    def body(state: list[Scalar]) -> tuple[list[Scalar], Scalar]:
        x, s, z, count, stopped, gap_prev, alpha_prev = unpack(state)
        frozen = gt(stopped, 0.5)
        if centred:  # a frame still going at RESTART_AT starts again from the cones' centres
            k = sub(count, restart_base[0])
            at = logical_and(gt(k, RESTART_AT - 0.5), gt(RESTART_AT + 0.5, k))
            again = logical_and(logical_not(frozen), at)
            x0_, s0_, z0_, *_ = unpack([*centre0, 0.0, 0.0, 0.0, 0.0])
            x = [select(again, a, b_) for a, b_ in zip(x0_, x, strict=True)]
            s = [[select(again, a, b_) for a, b_ in zip(s0_[k], s[k], strict=True)]
                 for k in range(m)]  # fmt: skip
            z = [[select(again, a, b_) for a, b_ in zip(z0_[k], z[k], strict=True)]
                 for k in range(m)]  # fmt: skip
            gap_prev = select(again, float("inf"), gap_prev)
            alpha_prev = select(again, ALPHA0, alpha_prev)
        x_new, s_new, z_new, alpha = _step(pb, x, s, z, alpha_prev)
        # ---- take the step unless it went non-finite or the frame has stopped
        ok = isfinite(sum_([*x_new, *(v for sk in s_new for v in sk),
                            *(v for zk in z_new for v in zk)]))  # fmt: skip
        keep = logical_or(frozen, logical_not(ok))
        x = [select(keep, a, b_) for a, b_ in zip(x, x_new, strict=True)]
        s = [[select(keep, a, b_) for a, b_ in zip(s[k], s_new[k], strict=True)] for k in range(m)]
        z = [[select(keep, a, b_) for a, b_ in zip(z[k], z_new[k], strict=True)] for k in range(m)]
        count = select(frozen, count, add(count, 1.0))
        if not centred:
            # ---- stop once the gap is far below eps |x|^2: later steps would only stir
            # rounding noise (W grows like 1 / sqrt(gap)) and could spoil the residuals
            gap = sum_([select(on[k], _dot(s[k], z[k]), 0.0) for k in range(m)])
            stall = logical_and(logical_not(gt(gap, gap_stall)), gt(gap, mul(0.5, gap_prev)))
            halt = logical_or(frozen, logical_or(logical_not(gt(gap, gap_stop)), stall))
        else:
            # ---- stop on the central path: a full step (the residuals of the linear
            # conditions vanish) that leaves s o z at nu e to rounding
            gap = _centrality(on, s, z, nu)
            full = logical_not(gt(1.0, alpha))
            stall = logical_and(logical_not(gt(gap, gap_stall)), gt(gap, mul(0.5, gap_prev)))
            near = logical_or(logical_not(gt(gap, gap_stop)), stall)
            halt = logical_or(frozen, logical_and(full, near))
        new = [*x, *(v for sk in s for v in sk), *(v for zk in z for v in zk), count,
               select(halt, 1.0, 0.0), select(frozen, gap_prev, gap), alpha]  # fmt: skip
        return new, halt

    def converged(state: Sequence[Scalar]) -> Scalar:
        x, s, z, _, stopped, _, _ = unpack(state)
        kkt = _converged(P, q, qq, cones, on, x, s, z, tol, nu if centred else 0.0, m_on)
        return logical_and(gt(stopped, 0.5), kkt)

    if x_start is None:
        start_on = False
    x0 = [select(start_on, a, b_) for a, b_ in zip(x_start or x_pinv, x_pinv, strict=True)]
    cold = [*start(list(x_pinv), False), 0.0, select(inside0, 1.0, 0.0), float("inf"), ALPHA0]
    init = cold if x_start is None else [*start(x0, start_on), *cold[-4:]]
    # the MAP objective: a frame restarted at RESTART_AT has the whole budget again (a budget
    # of at most RESTART_AT iterations has no restart)
    budget = iterations + RESTART_AT if centred and iterations > RESTART_AT else iterations
    state = loop(budget, body, init)
    if x_start is not None:
        # ---- a warm-started frame that did not converge starts again from x_pinv, cold, with
        # a budget of its own (its iterations add up)
        redo = logical_and(start_on, logical_not(converged(state)))
        redo = logical_and(redo, logical_not(inside0))
        count1 = state[u + 6 * m]
        restart_base[0] = count1
        init2 = [select(redo, a, b_) for a, b_ in zip(cold[: u + 6 * m], state[: u + 6 * m],
                                                     strict=True)]  # fmt: skip
        init2 += [count1, select(redo, 0.0, 1.0), select(redo, float("inf"), state[-2]), ALPHA0]
        state = loop(budget, body, init2)
    x, s, z, count, stopped, _, _ = unpack(state)
    # active: the slack is on the cone's boundary (or apex) to within ACTIVE_RTOL of its size
    # plus one unit (N), so a slack at the apex (size ~0) counts; the dual alone cannot tell, as
    # it is only eps-sized when the cone merely picks a point of the least-squares set
    rtol = 10.0 * tol
    active = [logical_and(o, logical_not(gt(_eig_min(sk), mul(rtol, add(sk[0], 1.0)))))
              for o, sk in zip(on, s, strict=True)]  # fmt: skip
    conv = converged(state)
    x = _apply_blocks(cones, None, Cinv, x, forward=False)
    x_pinv = _apply_blocks(cones, None, Cinv, x_pinv, forward=False)
    return ConeSolution(
        [select(inside0, a, b_) for a, b_ in zip(x_pinv, x, strict=True)],
        logical_or(inside0, conv),
        select(inside0, 0.0, count),
        [logical_and(logical_not(inside0), a) for a in active],
    )


def _centrality(on, s, z, nu: Scalar) -> Scalar:
    """``sum_k |s_k o z_k - nu e|^2`` over the cones that apply."""
    out: Scalar = 0.0
    for k in range(len(on)):
        sz = _jordan(s[k], z[k])
        d = [sub(sz[0], nu), sz[1], sz[2]]
        out = add(out, select(on[k], _dot(d, d), 0.0))
    return out


def _converged(P, q, qq, cones, on, x, s, z, tol: float, nu: Scalar = 0.0, m_on=1.0) -> Scalar:
    """Relative KKT residuals and duality gap below ``tol`` (squared norms, no square roots).

    With ``nu > 0``: ``|s o z - nu e|`` below ``tol nu`` per cone instead of the gap.
    """
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
    if is_const(nu) and nu == 0:
        ok_g = logical_not(gt(gap, mul(tol, add(1.0, qq))))
    else:
        ok_g = logical_not(gt(_centrality(on, s, z, nu), mul(t2, mul(mul(nu, nu), m_on))))
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
        x0: ``(*B, u)`` starting point (default ``pinv(A) b``, which is also the answer wherever
            it lies inside every cone).
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
    iters, eps, tol, stop = settings.resolved(A.dtype)
    Af = A.expand(*batch, R, u).reshape(n, R, u)
    bf = b.expand(*batch, R).reshape(n, R)
    xp = (torch.linalg.pinv(Af, rcond=1e-10) @ bf.unsqueeze(-1)).squeeze(-1)
    x0f = None if x0 is None else x0.expand(*batch, u).reshape(n, u)
    cs = []
    for k, (cols, C) in enumerate(cones):
        cols = tuple(int(c) for c in cols)
        if C.shape[-2:] != (3, len(cols)) or any(not 0 <= c < u for c in cols):
            raise InputError(f"cone {k}: C must be (*B, 3, {len(cols)}) over columns in [0, {u})")
        Cf = C.expand(*batch, 3, len(cols)).reshape(n, 3, len(cols))
        o = True if on is None else on.expand(*batch, len(cones)).reshape(n, -1)[:, k]
        cs.append(Cone(cols, [[Cf[:, r, j] for j in range(len(cols))] for r in range(3)], o))
    start = None if x0f is None else [x0f[:, j] for j in range(u)]
    start_on = True if x0f is None else torch.isfinite(x0f).all(-1)
    if x0f is not None:
        start = [torch.where(start_on, v, 0.0) for v in start]
    sol = solve_cones([[Af[:, r, j] for j in range(u)] for r in range(R)],
                      [bf[:, r] for r in range(R)], cs, [xp[:, j] for j in range(u)], eps,
                      iters, tol, stop, start, start_on)  # fmt: skip

    def t(v: Scalar, dtype=A.dtype) -> Tensor:
        return v.to(dtype) if isinstance(v, Tensor) else torch.full((n,), v, dtype=dtype)

    x = torch.stack([t(v) for v in sol.x], -1).reshape(*batch, u)
    act = (torch.stack([t(v, torch.bool) for v in sol.active], -1) if cones
           else torch.zeros(n, 0, dtype=torch.bool))  # fmt: skip
    return (x, t(sol.converged, torch.bool).reshape(batch),
            counts(t(sol.iterations)).reshape(batch),
            act.reshape(*batch, len(cones)))  # fmt: skip
