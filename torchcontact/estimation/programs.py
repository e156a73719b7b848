"""The estimator's stages chained into whole-frame programs, one per layout.

:func:`estimate_program` is everything :meth:`ContactEstimator.estimate` computes for a frame,
input checks included, so that a generated kernel (:mod:`torchcontact.kernels`) reads the raw
inputs once and writes every output once:

1. **status** (:data:`torchcontact.STATUS`): non-finite inputs, zero-length directions and
   implausible values set bits; such a frame computes on zeros and returns NaN;
2. the stages of :mod:`torchcontact.estimation.stages`;
3. outputs that come out non-finite from valid inputs (overflow) set bit 32 and become NaN.

:func:`predict_program` is the forward model (the readings known contacts would cause).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

from torchcontact import dynamics as _dyn
from torchcontact import kernels
from torchcontact import spatial as sp
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
from torchcontact.constrained import Cone, cone_rows, solve_cones
from torchcontact.contacts import KINDS
from torchcontact.estimation import stages
from torchcontact.estimation.layout import EstimationModel
from torchcontact.solve import cholesky, solve_program, tril_solve, weighted_solve_program
from torchcontact.status import Status

__all__ = ["ReadingCorrection", "estimate_program", "predict_program", "program"]


class ReadingCorrection(Protocol):
    """A correction of the readings inside :func:`estimate_program` (e.g. offset + inertial).

    Attributes:
        inputs: its input arrays, name -> scalars per frame.
        outputs: its output arrays, name -> scalars per frame (NaN in frames with a status).
        key: identifies its constants (part of the program's key).
    """

    inputs: dict[str, int]
    outputs: dict[str, int]
    key: str

    def apply(
        self, em: EstimationModel, x: dict[str, list], X: list, v: list, a: list, f: list,
        readings: list[list[Scalar]],
    ) -> tuple[list[list[Scalar]], dict[str, list[Scalar]]]:  # fmt: skip
        """Corrected readings (per sensor, 6 scalars) and the outputs, from the forward pass."""


_NAN = float("nan")


def _all(masks: Sequence[Scalar]) -> Scalar:
    out: Scalar = True
    for m in masks:
        out = logical_and(out, m)
    return out


def _any(masks: Sequence[Scalar]) -> Scalar:
    out: Scalar = False
    for m in masks:
        out = logical_or(out, m)
    return out


def _finite(xs: Sequence[Scalar]) -> Scalar:
    return _all([isfinite(x) for x in xs])


def _bit(m: Scalar, bit: Status) -> Scalar:
    return select(m, float(bit), 0.0)


def estimate_program(
    em: EstimationModel,
    moving_base: bool,
    torque_rows: bool,
    with_cov: bool,
    cones: tuple[int, float, float] | None = None,
    warm: bool = False,
    nullspace: bool = False,
    weighted: bool = False,
    tau_noise: bool = False,
    *,
    correction: ReadingCorrection | None = None,
    noise: Sequence[Sequence[float]] | None = None,
) -> kernels.Program:
    """The whole estimator of a layout as one program.

    Inputs (per frame, the names of :data:`torchcontact.onnx.format.INPUTS`, flattened):
    ``q, qd, qdd`` (nv), ``ft`` (6 S, sensor after sensor), ``positions`` (3K), ``active``
    (K, 0/1), ``directions`` (3K, with ``force_dir`` slots), ``wrenches`` (6K, with ``known``
    slots), ``omega, domega, proper_acc`` (3 each, moving base), ``tau_measured, tau_mask``
    (nv each, torque rows), ``ft_cov`` (36 S, with covariance or weights), ``tau_var`` (nv,
    ``tau_noise``: each measured torque's noise variance), ``normals`` (3K), ``friction`` and
    ``pushing``
    (K each, with ``cones``), ``warm`` (6K, force and moment per slot, with ``warm``). Outputs:
    ``force, moment`` (3K), ``tau`` (nv), ``rank, unknowns, residual`` (S), ``status`` (1),
    ``cov`` (36 K), ``converged, iterations`` (S) and ``cone_active`` (K) with ``cones``,
    ``nullspace`` (``sum_r u_r^2``, each region's ``u_r x u_r`` basis, row-major, columns the
    vectors) with ``nullspace``.

    With ``cones = (iterations, eps, tol)`` the contact wrenches are the friction-cone
    constrained estimate (:func:`torchcontact.constrained.solve_cones`, started from the
    pseudo-inverse solution, or from ``warm`` where it is finite); ``residual`` is then
    ``|A x - b|`` of that estimate and ``rank`` stays the rank of ``A``. Without ``cones``,
    ``warm`` and ``nullspace`` the program is exactly the unconstrained one (same kernel).

    A ``correction`` (:class:`ReadingCorrection`) adds its inputs and outputs and replaces the
    readings by its corrected ones after the forward pass (on whose values it may build).

    With ``weighted`` every region's rows are whitened by their noise covariance (``ft_cov``
    of its sensor, ``tau_var`` of its torque rows, unit variances without ``tau_noise``):
    :func:`torchcontact.solve.weighted_solve_program`, the constrained solve on the whitened
    rows; ``cov`` is then the covariance of the weighted estimate. Without it ``ft_cov`` (and
    ``tau_var``) are only propagated to ``cov``.

    With ``noise`` (per sensor 6 standard deviations ``[N; N m]``, a diagonal covariance fixed
    in the program: an exported graph's or C library's ``--ft-noise``) the solve is weighted by
    these constants instead of the ``ft_cov`` input, the same whitening; ``ft_cov`` is then an
    input only with ``with_cov``, the frame's noise propagated through the weighted solve.
    """
    if noise is not None:
        weighted = True
        noise = tuple(tuple(float(v) for v in sd) for sd in noise)
        if len(noise) != len(em.sensors) or any(len(sd) != 6 for sd in noise):
            raise ValueError(f"noise: 6 standard deviations per sensor ({len(em.sensors)})")
    S, K, nv = len(em.sensors), len(em.slots), em.tree.nv
    kinds = em.kinds
    has_dir = "force_dir" in kinds
    has_known = "known" in kinds
    inputs = {"q": nv, "qd": nv, "qdd": nv}
    inputs.update(ft=6 * S, positions=3 * K, active=K)
    if has_dir:
        inputs["directions"] = 3 * K
    if has_known:
        inputs["wrenches"] = 6 * K
    if moving_base:
        inputs.update(omega=3, domega=3, proper_acc=3)
    if torque_rows:
        inputs.update(tau_measured=nv, tau_mask=nv)
    if with_cov or (weighted and noise is None):
        inputs["ft_cov"] = 36 * S
    if tau_noise and torque_rows:
        inputs["tau_var"] = nv
    if cones is not None:
        inputs.update(normals=3 * K, friction=K, pushing=K)
        if warm:
            inputs["warm"] = 6 * K
    outputs = {"force": 3 * K, "moment": 3 * K, "tau": nv, "rank": S, "unknowns": S,
               "residual": S, "status": 1}  # fmt: skip
    if with_cov:
        outputs["cov"] = 36 * K
    if cones is not None:
        outputs.update(converged=S, iterations=S, cone_active=K)
    n_unknowns = [sum(KINDS[em.slots[k].kind] for k in reg.slots) for reg in em.regions]
    if nullspace:
        outputs["nullspace"] = sum(u * u for u in n_unknowns)
    if correction is not None:
        inputs.update(correction.inputs)
        outputs.update(correction.outputs)

    def fn(x: dict[str, list]) -> dict[str, list]:
        readings = [x["ft"][6 * i : 6 * i + 6] for i in range(S)]
        act_in = [gt(a, 0.5) for a in x["active"]]
        pos = [x["positions"][3 * k : 3 * k + 3] for k in range(K)]
        dirs = [x["directions"][3 * k : 3 * k + 3] for k in range(K)] if has_dir else None
        wr = [x["wrenches"][6 * k : 6 * k + 6] for k in range(K)] if has_known else None
        base_keys = ("omega", "domega", "proper_acc") if moving_base else ()
        # ---- status of the inputs (STATUS bits)
        b1 = logical_not(_finite([v for r in readings for v in r]))
        joint = [*x["q"], *x["qd"], *x["qdd"], *(v for k in base_keys for v in x[k])]
        b2 = logical_not(_finite(joint))
        bad_field, zero_dir = [], []
        for k, kind in enumerate(kinds):
            fields = list(pos[k])
            if kind == "force_dir":
                fields += list(dirs[k])
                n2 = sum_([mul(v, v) for v in dirs[k]])
                zero = logical_and(isfinite(n2), logical_not(gt(n2, 0.0)))
                zero_dir.append(logical_and(act_in[k], zero))
            if kind == "known":
                fields += list(wr[k])
            if cones is not None and kind in ("force", "wrench"):
                push = gt(x["pushing"][k], 0.5)
                nk = x["normals"][3 * k : 3 * k + 3]
                cone_fields = [*nk, x["friction"][k]]
                fields.append(select(push, sum_(cone_fields), 0.0))  # NaN/inf propagate
                n2 = sum_([mul(v, v) for v in nk])
                zero = logical_and(push, logical_and(isfinite(n2), logical_not(gt(n2, 0.0))))
                zero_dir.append(logical_and(act_in[k], zero))
            bad_field.append(logical_and(act_in[k], logical_not(_finite(fields))))
        b4, b8 = _any(bad_field), _any(zero_dir)
        b16: Scalar = False
        if torque_rows:
            pairs = zip(x["tau_measured"], x["tau_mask"], strict=True)
            b16 = _any([logical_and(gt(m, 0.5), logical_not(isfinite(t))) for t, m in pairs])
        implausible = []
        if em.velocity_limit is not None:
            for v, lim in zip(x["qd"], em.velocity_limit, strict=True):
                if lim != float("inf"):
                    implausible += [gt(v, lim), gt(neg(v), lim)]
        for r, rng in zip(readings, em.ft_range, strict=True):
            if rng is not None:
                for v, lim in zip(r, rng, strict=True):
                    implausible += [gt(v, lim), gt(neg(v), lim)]
        before = _any([b1, b2, b4, b8, b16])
        b64 = logical_and(logical_not(before), _any(implausible))
        ok = logical_not(logical_or(before, b64))
        status = sum_(
            [
                _bit(b1, Status.FT_NONFINITE),
                _bit(b2, Status.JOINT_NONFINITE),
                _bit(b4, Status.CONTACT_NONFINITE),
                _bit(b8, Status.ZERO_DIRECTION),
                _bit(b16, Status.TORQUE_NONFINITE),
                _bit(b64, Status.IMPLAUSIBLE),
            ]
        )

        # a bad frame computes on zeros (its outputs become NaN below)
        def clean(v: Scalar) -> Scalar:
            return select(logical_and(ok, isfinite(v)), v, 0.0)

        act = [select(logical_and(ok, a), 1.0, 0.0) for a in act_in]
        q, qd, qdd = ([clean(v) for v in x[k]] for k in ("q", "qd", "qdd"))
        readings = [[clean(v) for v in r] for r in readings]
        pos = [[clean(v) for v in p] for p in pos]
        dirs = [[clean(v) for v in d] for d in dirs] if has_dir else None
        wr = [[clean(v) for v in w] for w in wr] if has_known else None
        base = {k: [clean(v) for v in x[k]] for k in base_keys} if moving_base else None
        tau_meas = tau_mask = None
        if torque_rows:
            tau_meas = [clean(v) for v in x["tau_measured"]]
            tau_mask = [select(logical_and(ok, gt(m, 0.5)), 1.0, 0.0) for m in x["tau_mask"]]

        # ---- the stages
        X, vel, acc, f = stages.forward(em, q, qd, qdd, base)
        corrected: dict[str, list] = {}
        if correction is not None:  # the readings less what the model and its layers explain
            readings, corrected = correction.apply(em, x, X, vel, acc, f, readings)
        known: dict[int, list] = {}
        for k, slot in enumerate(em.slots):
            if slot.kind == "known":
                w = (tuple(mul(act[k], v) for v in wr[k][:3]),
                     tuple(mul(act[k], v) for v in wr[k][3:]))  # fmt: skip
                known.setdefault(slot.body, []).append(
                    stages.wrench_on_body(slot, stages.contact_point(slot, pos[k]), w)
                )
        _, tau_b, b = stages.region_rhs(em, X, f, readings, known, tau_meas, tau_mask)
        maps, grams = stages.contact_maps(em, X, pos, dirs, act, tau_mask)
        # ---- the rows' noise: per region its covariance (sensor block, torque variances) and,
        # to whiten by, its Cholesky factor; a bad frame gets unit noise (its outputs are NaN)
        sigmas: list = [None] * S
        chol: list = [None] * S
        if with_cov or weighted:
            eye = [1.0 if i == j else 0.0 for i in range(6) for j in range(6)]
            for r, reg in enumerate(em.regions):
                rows = list(reg.torque_coords) if torque_rows else []
                Rr = 6 + len(rows)

                def block(sig6: list, rows: list = rows, Rr: int = Rr) -> list[list]:
                    sig = [[sig6[6 * i + j] if i < 6 and j < 6 else 0.0 for j in range(Rr)]
                           for i in range(Rr)]  # fmt: skip
                    for t, c in enumerate(rows):
                        if tau_noise:
                            v = x["tau_var"][c]
                            good = logical_and(ok, logical_and(isfinite(v), gt(v, 0.0)))
                            sig[6 + t][6 + t] = select(good, v, 1.0)
                        else:  # unknown: unit weight, nothing to propagate
                            sig[6 + t][6 + t] = 1.0 if weighted else 0.0
                    return sig

                sig = None
                if "ft_cov" in x:
                    ft_cov = x["ft_cov"][36 * r : 36 * r + 36]
                    sig = block([select(ok, v, e) for v, e in zip(ft_cov, eye, strict=True)])
                sigmas[r] = sig
                if noise is not None:  # constants: the exported noise
                    var = [noise[r][i] ** 2 if i == j else 0.0 for i in range(6) for j in range(6)]
                    chol[r] = cholesky(block(var))
                elif weighted:
                    chol[r] = cholesky(sig)
        ys, ranks, resid, factors = [], [], [], []
        for r, reg in enumerate(em.regions):
            if all(em.slots[k].kind == "known" for k in reg.slots):  # nothing to solve
                ys.append([0.0] * len(b[r]))
                ranks.append(0.0)
                resid.append(sqrt(sum_([mul(v, v) for v in b[r]])))
                factors.append(None)
                continue
            if weighted:
                y, rank, res, fac = weighted_solve_program(grams[r], b[r], chol[r], em.rank_rtol)
            else:
                y, rank, res, fac = solve_program(grams[r], b[r], em.rank_rtol)
            ys += [y]
            ranks += [rank]
            resid += [res]
            factors += [fac]
        extra: dict[str, list] = {}
        if cones is not None or nullspace:
            resid, w, extra = _constrained_and_nullspace(
                em, x, clean, maps, b, ys, factors, ranks, resid, wr, act, cones, warm,
                nullspace, chol,
            )  # fmt: skip
        else:
            w = stages.contact_wrenches(em, maps, ys, wr, act)
        tau = stages.backward(em, X, tau_b, pos, w)
        force = [v for wk in w for v in wk[0]]
        moment = [v for wk in w for v in wk[1]]
        cov = None
        if with_cov:
            cov = [v for c in stages.covariance(em, maps, factors, sigmas, chol) for v in c]

        # ---- outputs: non-finite from valid inputs is bit 32; bad frames give NaN
        b32 = logical_and(ok, logical_not(_finite([*force, *moment, *tau, *resid])))
        bad = logical_not(logical_and(ok, logical_not(b32)))

        def out(v: Scalar) -> Scalar:
            return select(bad, _NAN, v)

        n_unk = [sum_([select(act_in[k], float(KINDS[em.slots[k].kind]), 0.0)
                       for k in reg.slots]) for reg in em.regions]  # fmt: skip
        result = {
            "force": [out(v) for v in force],
            "moment": [out(v) for v in moment],
            "tau": [out(v) for v in tau],
            "rank": ranks,
            "unknowns": n_unk,
            "residual": [out(v) for v in resid],
            "status": [add(status, _bit(b32, Status.OUTPUT_NONFINITE))],
        }
        if cones is not None:  # a region's constrained solve did not converge
            unconv = _any([logical_not(gt(v, 0.5)) for v in extra["converged"]])
            unconv = _bit(logical_and(ok, unconv), Status.NOT_CONVERGED)
            result["status"] = [add(result["status"][0], unconv)]
        if with_cov:
            result["cov"] = [out(v) for v in cov]
        if cones is not None:
            result["converged"] = extra["converged"]
            result["iterations"] = extra["iterations"]
            result["cone_active"] = extra["cone_active"]
        if nullspace:
            result["nullspace"] = [out(v) for v in extra["nullspace"]]
        result.update({k: [out(v) for v in vs] for k, vs in corrected.items()})
        return result

    key = f"est|{em.key}|{moving_base}|{torque_rows}|{with_cov}"
    if cones is not None or nullspace:
        key += f"|cones={cones}|warm={warm}|null={nullspace}"
    if correction is not None:
        key += f"|corr={correction.key}"
    if weighted or tau_noise:
        key += f"|weighted={weighted}|tau_noise={tau_noise and torque_rows}"
    if noise is not None:
        key += f"|noise={noise}"
    return kernels.Program("estimator", fn, inputs, outputs, key)


def _constrained_and_nullspace(em, x, clean, maps, b, ys, factors, ranks, resid, wr, act, cones,
                               warm, nullspace, chol):  # fmt: skip
    """The constrained estimate and/or the null-space bases of every region (program part).

    ``chol``: per region the Cholesky factor of its rows' noise covariance, or None (unweighted):
    the cone solver then sees the whitened rows ``c L^-1 A``, ``c L^-1 b``, with ``c`` the scale
    that keeps the largest row norm of ``A`` (the solver's ``eps`` and stopping rule are relative
    to the problem's scale; ``c`` leaves the weighted least-squares problem unchanged).
    """
    K = len(em.slots)
    w = stages.contact_wrenches(em, maps, ys, wr, act)  # pinv (and known) wrenches
    extra: dict[str, list] = {"converged": [], "iterations": [], "cone_active": [False] * K,
                              "nullspace": []}  # fmt: skip
    resid = list(resid)
    for r, reg in enumerate(em.regions):
        n_unk = sum(KINDS[em.slots[k].kind] for k in reg.slots)
        if factors[r] is None:  # only known slots: nothing to solve
            extra["converged"].append(1.0)
            extra["iterations"].append(0.0)
            continue
        A, labels = stages.contact_matrix(em, maps, r)
        R, u = len(A), len(labels)
        n_unk_r = sum_([select(gt(act[k], 0.5), float(KINDS[em.slots[k].kind]), 0.0)
                        for k in reg.slots])  # fmt: skip
        Aw, bw = A, b[r]  # the rows the solve weighs (whitened when weighted)
        if chol[r] is not None:
            cols = [tril_solve(chol[r], [A[i][j] for i in range(R)]) for j in range(u)]
            Aw = [[cols[j][i] for j in range(u)] for i in range(R)]
            bw = tril_solve(chol[r], b[r])
        if nullspace:
            present = [act[k] for k, _ in labels]
            rtol = 10.0 * math.sqrt(em.rank_rtol)
            basis = stages.nullspace_basis(Aw, factors[r], present, rtol)
            extra["nullspace"] += [basis[c][i] for i in range(n_unk) for c in range(n_unk)]
        if cones is None:
            continue
        iterations, eps, tol, stop, *rest = cones
        prior = rest[0] if rest else None
        x0 = [sum_([mul(A[i][j], ys[r][i]) for i in range(R)]) for j in range(u)]  # pinv(A) b
        x_start, start_on = None, False
        if warm:
            xw = []
            for k, j in labels:
                wk = [clean(v) for v in x["warm"][6 * k : 6 * k + 6]]
                if em.slots[k].kind == "force_dir":
                    d = x["directions"][3 * k : 3 * k + 3]
                    n2 = sum_([mul(v, v) for v in d])
                    xw.append(div(sum_([mul(d[i], wk[i]) for i in range(3)]),
                                  sqrt(select(gt(n2, 0.0), n2, 1.0))))  # fmt: skip
                else:
                    xw.append(wk[j])
            fin = _finite([v for k in dict.fromkeys(k for k, _ in labels)
                           for v in x["warm"][6 * k : 6 * k + 6]])  # fmt: skip
            x_start, start_on = xw, fin
        cone_list, cone_slot = [], []
        start = 0
        for k in reg.slots:
            slot = em.slots[k]
            if slot.kind == "known":
                continue
            on = logical_and(gt(act[k], 0.5), gt(x["pushing"][k], 0.5))
            if slot.kind == "force_dir":
                cone_list.append(Cone((start,), [[1.0], [0.0], [0.0]], on))
            else:
                n_in = x["normals"][3 * k : 3 * k + 3]
                nk = [select(on, clean(v), d) for v, d in zip(n_in, (0.0, 0.0, 1.0), strict=True)]
                mu = select(on, clean(x["friction"][k]), 1.0)
                cone_list.append(Cone(tuple(range(start, start + 3)), cone_rows(nk, mu), on))
            cone_slot.append(k)
            start += KINDS[slot.kind]
        As, bs = A, b[r]
        if chol[r] is not None:  # the whitened rows, scaled back to the size of A's

            def rowmax(M):
                out: Scalar = 0.0
                for row in M:
                    n2 = sum_([mul(v, v) for v in row])
                    out = select(gt(n2, out), n2, out)
                return out

            big, big_w = rowmax(A), rowmax(Aw)
            c = sqrt(div(select(gt(big_w, 0.0), big, 1.0), select(gt(big_w, 0.0), big_w, 1.0)))
            As = [[mul(c, v) for v in row] for row in Aw]
            bs = [mul(c, v) for v in bw]
        else:
            c = 1.0 if prior is None else prior[3]  # unweighted: A = sigma (A / sigma)
        nu: Scalar = 0.0
        ridge: Scalar = 0.0
        exact: Scalar = True
        if prior is not None:
            # the MAP estimate (ForcePrior): the data term of the scaled rows is c^2 times the
            # negative log-likelihood, so the prior's terms are scaled alike
            c2 = mul(c, c)
            p_nu, p_scale, p_rel, _ = prior
            nu = mul(c2, p_nu)
            if p_scale is not None:
                lam: Scalar = 1.0 / (p_scale * p_scale)
            else:
                m_push = sum_([select(cn.on, 1.0, 0.0) for cn in cone_list])
                s2 = mul(p_rel * p_rel, div(_dot(x0, x0), _maxs(m_push, 1.0)))
                lam = div(1.0, add(s2, _TINY_SCALE2))
            # eps + ridge = c^2 (1 / s^2 + eps): eps joins the Gaussian, unscaled by c
            ridge = sub(mul(c2, add(lam, eps)), eps)
            exact = logical_not(gt(sub(n_unk_r, ranks[r]), 0.5))
        sol = solve_cones(As, bs, cone_list, x0, eps, iterations, tol, stop, x_start, start_on,
                          nu, ridge, exact)  # fmt: skip
        extra["converged"].append(select(sol.converged, 1.0, 0.0))
        extra["iterations"].append(sol.iterations)
        for k, a in zip(cone_slot, sol.active, strict=True):
            extra["cone_active"][k] = select(a, 1.0, 0.0)
        # the constrained wrenches replace the pseudo-inverse ones (link frame, about the point)
        start = 0
        for k in reg.slots:
            slot = em.slots[k]
            if slot.kind == "known":
                continue
            xs = sol.x[start : start + KINDS[slot.kind]]
            if slot.kind == "force_dir":
                w[k] = (sp.v_scale(mul(act[k], xs[0]), maps[k].d), sp.ZERO3)
            elif slot.kind == "force":
                w[k] = (tuple(mul(act[k], v) for v in xs), sp.ZERO3)
            else:
                w[k] = (tuple(mul(act[k], v) for v in xs[:3]),
                        tuple(mul(act[k], v) for v in xs[3:]))  # fmt: skip
            start += KINDS[slot.kind]
        res = [sub(sum_([mul(A[i][j], sol.x[j]) for j in range(u)]), b[r][i]) for i in range(R)]
        resid[r] = sqrt(sum_([mul(v, v) for v in res]))
    return resid, w, extra


#: Floor of the data-driven prior scale ``s^2`` (N^2): a frame without load gets forces ~1 mN.
_TINY_SCALE2 = 1e-6


def _dot(a: Sequence[Scalar], b: Sequence[Scalar]) -> Scalar:
    return sum_([mul(u, v) for u, v in zip(a, b, strict=True)])


def _maxs(a: Scalar, b: Scalar) -> Scalar:
    return select(gt(a, b), a, b)


def predict_program(em: EstimationModel, moving_base: bool) -> kernels.Program:
    """The forward model: every sensor's reading for given contact wrenches.

    Inputs: ``q, qd, qdd`` (nv), ``positions`` (3K), ``wrenches`` (6K, link frame, about the point),
    ``active`` (K), base motion (moving base). Output: ``ft`` (6 S), sensor frames and directions.
    """
    S, K, nv = len(em.sensors), len(em.slots), em.tree.nv
    inputs = {"q": nv, "qd": nv, "qdd": nv, "positions": 3 * K, "wrenches": 6 * K, "active": K}
    if moving_base:
        inputs.update(omega=3, domega=3, proper_acc=3)

    def fn(x: dict[str, list]) -> dict[str, list]:
        base = {k: x[k] for k in ("omega", "domega", "proper_acc")} if moving_base else None
        X, _, _, f = stages.forward(em, x["q"], x["qd"], x["qdd"], base)
        f = list(f)
        for k, slot in enumerate(em.slots):
            wk = [mul(x["active"][k], v) for v in x["wrenches"][6 * k : 6 * k + 6]]
            point = stages.contact_point(slot, x["positions"][3 * k : 3 * k + 3])
            wb = stages.wrench_on_body(slot, point, (tuple(wk[:3]), tuple(wk[3:])))
            f[slot.body] = (sp.v_sub(f[slot.body][0], wb[0]), sp.v_sub(f[slot.body][1], wb[1]))
        F, _ = _dyn.backward_pass(em.tree, X, f)
        out = []
        for reg in em.regions:
            Fs = sp.force_to_child(reg.T_child_sensor, F[reg.child])
            out += [mul(reg.sign, v) for v in (*Fs[0], *Fs[1])]
        return {"ft": out}

    return kernels.Program("predict", fn, inputs, {"ft": 6 * S}, f"pred|{em.key}|{moving_base}")


def program(em: EstimationModel, name: str, *flags, **options) -> kernels.Program:
    """The cached program ``name`` (``"estimate"`` or ``"predict"``) of a layout."""
    key = (name, *flags, *sorted(options.items()))
    if key not in em._programs:
        make = {"estimate": estimate_program, "predict": predict_program}[name]
        em._programs[key] = make(em, *flags, **options)
    return em._programs[key]
