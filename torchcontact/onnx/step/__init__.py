"""The single-frame estimator graph: the whole estimator in a few hundred ONNX nodes.

:func:`torchcontact.onnx.export_estimator` writes two graphs per layout. The *batched* one
(:mod:`torchcontact.onnx.batched`) is the estimator program emitted node by node: thousands of
nodes, each running over ``N`` frames. For one frame, onnxruntime's cost is per node (0.5-1 µs
measured here, whatever the tensor sizes of this graph), so the *step* graph is built
differently: every stage runs on all bodies (or slots) at once, with the tree folded into
constant matrices, and the solve works on whole matrices. Its stages, one module each, are the
stages of :mod:`torchcontact.estimation.stages` (Del Prete et al., HRI 2012, Sec. 2):

1. :mod:`~torchcontact.onnx.step.inputs`: the packed input, its checks, the status bits;
2. :mod:`~torchcontact.onnx.step.kinematics`: poses, motion and body wrenches (``forward``);
3. :mod:`~torchcontact.onnx.step.regions`: transmitted wrenches, ``b``, slot geometry and Gram
   matrices (``region_rhs``, ``contact_maps``);
4. :mod:`~torchcontact.onnx.step.solve`: the minimum-norm solve (:mod:`torchcontact.solve`),
   noise-weighted by constants in a graph exported with ``ft_noise``;
5. :mod:`~torchcontact.onnx.step.outputs`: contact wrenches, torques, the packed output
   (``contact_wrenches``, ``backward``, ``covariance``);

with :mod:`~torchcontact.onnx.step.corrections` subtracting chained F/T corrections and, in a
graph exported with ``online``, :mod:`~torchcontact.onnx.step.online` taking the offsets and
inertial changes as inputs and returning the model's reading and the payload regressors. The stages
share one :class:`~torchcontact.onnx.step.context.StepContext`. Each bilinear stage is generated
by tracing :mod:`torchcontact.spatial` code on symbols
(:func:`torchcontact.onnx.builder.bilinear`); nothing here is written for a particular robot.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from torchcontact.estimation.layout import EstimationModel
from torchcontact.onnx.builder import GraphBuilder, fold_linear_chains
from torchcontact.onnx.format import StepLayout
from torchcontact.onnx.step import corrections, inputs, kinematics, outputs, regions, solve
from torchcontact.onnx.step import online as online_stage
from torchcontact.onnx.step.context import Flags, StepContext

__all__ = ["Flags", "StepContext", "build_step_graph", "context", "stages"]


def context(em: EstimationModel, flags: Flags, dtype, residuals: Sequence = (),
            coords: Sequence[int] | None = None, online: Sequence = (),
            noise: Sequence[Sequence[float]] | None = None) -> StepContext:  # fmt: skip
    """The :class:`StepContext` of a layout: pruned tree, packed input layout, graph builder.

    Args:
        em: the layout.
        flags: the optional inputs.
        dtype: float32 or float64.
        residuals: ``[(ResidualGraph, onnx.ModelProto)]`` corrections to chain.
        coords: the joint coordinates whose torques to compute (None: all).
        online: per sensor its :class:`~torchcontact.online.state.SensorLayout`: the online
            inputs and outputs (:mod:`~torchcontact.onnx.step.online`); empty: none.
        noise: per sensor 6 standard deviations ``[N; N m]``: the weighted solve; None: none.
    """
    if noise is not None:
        noise = tuple(tuple(float(v) for v in sd) for sd in noise)
    coords = tuple(range(em.tree.nv)) if coords is None else tuple(coords)
    extra = tuple(dict.fromkeys(c for rg, _ in residuals for c in rg.extra))
    ctx = StepContext(em.prune(coords), em, tuple(em.kept_bodies(coords)), coords, flags,
                      GraphBuilder(dtype, "torchcontact_step"), StepLayout(), extra,
                      tuple(online), noise)  # fmt: skip
    states = [(rg.sensor, tuple(rg.state_shape)) for rg, _ in residuals if rg.state_shape]
    for name, shape in inputs.fields(ctx.em, flags, extra if residuals else (), states):
        ctx.lay.add(name, shape)
    for name, shape in online_stage.fields(ctx):
        ctx.lay.add(name, shape)
    return ctx


def build_step_graph(
    em: EstimationModel,
    moving_base: bool = False,
    torque_rows: bool = False,
    with_cov: bool = False,
    dtype=np.float64,
    residuals: Sequence = (),
    coords: Sequence[int] | None = None,
    online: Sequence = (),
    noise: Sequence[Sequence[float]] | None = None,
):
    """The single-frame graph of a layout.

    Args:
        em: the estimation model (robot, sensors, slots).
        moving_base: inputs ``omega, domega, proper_acc`` (IMU on the root body).
        torque_rows: inputs ``tau_measured, tau_mask``: measured joint torques add equations.
        with_cov: input ``ft_cov`` and output ``covariance``.
        dtype: float32 or float64.
        residuals: ``[(ResidualGraph, onnx.ModelProto)]`` corrections to chain (inputs
            ``extra``, ``h_in.<sensor>``; outputs ``h_out.<sensor>``).
        coords: the joint coordinates whose torques to compute
            (:meth:`EstimationModel.torque_joints`; the others are NaN); the graph keeps only
            the bodies these and the regions need.
        online: per sensor its :class:`~torchcontact.online.state.SensorLayout`: inputs
            ``bias``, ``theta.<sensor>``, outputs ``ft_model``, ``regressor.<sensor>``
            (:mod:`~torchcontact.onnx.step.online`).
        noise: per sensor 6 standard deviations ``[N; N m]``: each sensor's rows whitened by
            them, constants of the graph (:mod:`~torchcontact.onnx.step.solve`); None: the
            unweighted ``pinv(A) b``.

    Returns:
        ``(model, input layout, output layout)``: the graph has one input ``x`` ``(1, F)`` and
        one output ``out`` ``(1, O)``, packed as the layouts say.
    """
    ctx = context(em, Flags(moving_base, torque_rows, with_cov), dtype, residuals, coords,
                  online, noise)  # fmt: skip
    x = ctx.gb.input("x", [1, ctx.lay.size])
    v = stages(ctx, x, residuals)
    lay_out = outputs.pack(ctx, v["fm"], v["tau"], v["rank"], v["resid"], v["actK"],
                           v["status"], v["e"], v["idx"], v["states"], v["more"])  # fmt: skip
    fold_linear_chains(ctx.gb)  # products of the model's constant matrices, taken once
    return ctx.gb.model(), ctx.lay, lay_out


def stages(ctx: StepContext, x: str, residuals: Sequence = ()) -> dict:
    """Emit every stage on the packed input ``x``; returns the graph values by stage.

    Keys: ``status`` (the inputs' bits), ``T``, ``TP`` (poses), ``VA`` (motion), ``f0`` (body
    wrenches), ``W0`` (readings, root frame), ``Fb`` (transmitted wrenches), ``b``, ``G`` (per
    region), ``y``, ``rank``, ``resid`` (per region), ``fm`` (contact wrenches), ``tau``,
    ``ft_model`` and ``regressors`` (online graphs, else None), and what packing the output
    needs (``e``, ``idx``, ``actK``, ``states``, ``more``). The stage tests read them;
    :func:`build_step_graph` packs the output from them.
    """
    from torchcontact.onnx.batched import chain_corrections

    gb, em = ctx.gb, ctx.em
    wiring = corrections.Wiring(ctx, x)
    # ---- corrections: native stacks (built on this graph's forward pass) or inlined graphs
    native = {r: (rg, st) for r, (rg, model) in enumerate(residuals)
              if (st := corrections.native_stack(ctx, rg, model)) is not None}  # fmt: skip
    chained = chain_corrections(gb, residuals, wiring.select, wiring.state_in, skip=set(native))
    total = None
    if chained:
        total = None
        for _r, rg, c, h in chained:
            d = gb.op("MatMul", c, gb.f(wiring.project(rg.sensor)))
            total = d if total is None else gb.op("Add", total, d)
            if h is not None:
                wiring.state_out(rg, h)
        x = gb.op("Sub", x, total)
    # ---- 1. inputs: checks, status bits, affine entries
    ea, idx = inputs.plan(ctx)
    corrections.feature_entries(ctx, wiring, native, ea)  # the learned layers' angles
    idx.update(one=ea.one, zero=ea.zero, n_entries=len(ea.cols))
    chk = inputs.check(ctx, x, ea, idx)
    e = chk.e
    # ---- 2. poses, motion, body wrenches
    ce = gb.op("Cos", e)  # the joint angles' cos and sin (and the learned layers' features)
    wiring.angles(ce, idx["n_entries"])
    T = kinematics.poses(ctx, e, idx, ea.zero, ce)
    TP = kinematics.pose_features(ctx, T)
    base = None if ctx.flags.moving_base else np.array([[ea.value(k) for k in idx["base"]]])
    S0 = kinematics.subspaces(ctx, TP)  # (nb, 6) motion subspaces, root frame
    VA = kinematics.motion(ctx, TP, e, idx, base, S0)
    # the native stacks' inertial changes: more columns of the body wrenches' two stages
    deltas = [st.delta for _rg, st in native.values() if st.delta]
    f0, VAb, F = kinematics.body_wrenches(ctx, TP, VA, deltas)
    ws_corr, onl, cres = None, None, []
    if ctx.online:  # offsets and inertial changes as inputs: the model's reading, Y theta
        onl = online_stage.model_terms(ctx, e, idx, TP, VAb, f0)
        ws_corr = onl.ws_corr
    if native:  # the corrections come off the readings before these move to the root frame
        cres, ws_n = corrections.native_corrections(ctx, wiring, native, TP, VAb, f0, F)
        if ws_n is not None:
            ws_corr = ws_n if ws_corr is None else gb.op("Add", ws_corr, ws_n)
    W0 = kinematics.readings_root(ctx, TP, e, idx, cres)
    if onl is not None:
        W0 = gb.op("Sub", W0, onl.delta_root)
    ft_model, more = None, []
    if onl is not None:  # ft_model: every correction but the offset (learned, chained)
        ft_model = onl.ft_model
        if native and ws_n is not None:  # the learned layers, reading sense (sign ws)
            signs = np.array([[reg.sign] for reg in em.regions])
            ft_model = gb.op("Add", ft_model, gb.op("Mul", ws_n, gb.f(signs)))
        if total is not None:  # inlined correction graphs: their part of ft
            a, b, _ = ctx.lay.span("ft")
            chain_ft = gb.op("Slice", total, gb.i([a]), gb.i([b]), gb.i([1]))
            ft_model = gb.op("Add", ft_model, gb.op("Reshape", chain_ft, gb.i([ctx.S, 6])))
        more = [
            ([("ft_model", (ctx.S, 6))], gb.op("Reshape", ft_model, gb.i([1, 6 * ctx.S]))),
            ([(f"regressor.{lay.name}", (6, 10)) for lay in ctx.online], onl.regressors),
        ]
    # ---- 3. regions: transmitted wrenches, slot geometry, known contacts, b, Gram matrices
    Fb = regions.transmitted(ctx, f0, W0)
    Cg = regions.slot_geometry(ctx, TP, e, idx)
    s_rows, pairs = (regions.torque_row_coefs(ctx, TP, S0, e, idx) if ctx.flags.torque_rows
                     else (None, []))  # fmt: skip
    DB = gb.f(ctx.cut @ ctx.slot_bodies)
    known = "known" in ctx.kinds
    if known:  # given contact wrenches act like body wrenches: subtract
        known_s = regions.known_wrenches(ctx, Cg, e, idx, chk.actK)
        Fb = gb.op("Gemm", DB, regions.slots_to_root(ctx, TP, known_s), Fb, alpha=-1.0)
    b_all = regions.region_b(ctx, TP, Fb, S0, e, idx, ws_corr)
    gr = regions.grams(ctx, Cg, e, idx, chk.actK, s_rows, pairs)
    # ---- 4. solve, region by region
    ys, ranks, resids = [], [], []
    ncols = 7 if ctx.flags.covariance else 1
    for r, reg in enumerate(em.regions):
        R = 6 + (len(reg.torque_coords) if ctx.flags.torque_rows else 0)
        if all(em.slots[k].kind == "known" for k in reg.slots):
            ys.append(None)
            ranks.append(gb.f([[0.0]]))
            resids.append(gb.op("ReduceSumSquare", b_all[r], keepdims=1))
            continue
        possible = solve.full_rank_possible(ctx, reg, R, chk.actK)
        y, rank = solve.solve_region(ctx, gr.G[r], b_all[r], R, solve.min_rank(ctx, reg), ncols,
                                     ctx.whitening(r, R), possible)  # fmt: skip
        ys.append(y)
        ranks.append(rank)
        y1 = y if ncols == 1 else gb.op("Slice", y, gb.i([0]), gb.i([1]), gb.i([1]))
        res = gb.op("Sub", b_all[r], gb.op("MatMul", gr.G[r], y1))
        resids.append(gb.op("ReduceSumSquare", res, keepdims=1))
    # ---- 5. contact wrenches, torques, outputs
    fm = outputs.contact_wrenches(ctx, gr, ys, s_rows, pairs, e, idx, chk.actK, known)
    F_tot = Fb
    if ctx.K:  # the estimated (and known) contacts' wrenches leave the transmitted ones
        ws = gb.op("Slice", fm, gb.i([0, 6]), gb.i([ctx.K, 12]), gb.i([0, 1]))
        F_tot = gb.op("Gemm", DB, regions.slots_to_root(ctx, TP, ws), Fb, alpha=-1.0)
    tau = outputs.torques(ctx, S0, F_tot)
    return dict(status=chk.status, T=T, TP=TP, VA=VA, f0=f0, W0=W0, Fb=Fb, b=b_all, G=gr.G,
                y=ys, rank=ranks, resid=resids, fm=fm, tau=tau, e=e, idx=idx, actK=chk.actK,
                states=wiring.states, ft_model=ft_model,
                regressors=None if onl is None else onl.regressors, more=more)  # fmt: skip
