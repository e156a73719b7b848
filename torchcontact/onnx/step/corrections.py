"""Corrections in the single-frame graph: chained correction graphs and native stacks.

A correction ``c`` (sensor frame and measure direction) is subtracted from its sensor's reading.
Correction graphs are inlined and fed through the one wiring of
:func:`torchcontact.onnx.batched.chain_corrections`. A correction stack that carries its layers
(``stack`` metadata, :func:`torchcontact.onnx.export.export_residual_checkpoint`) is built
*natively* on this graph's own forward pass instead: the offset, the inertial layer as the
subtree's Newton-Euler wrenches with the parameter change as inertias, the nominal-wrench feature
from the body wrenches; only the learned network is inlined (a few nodes instead of the
thousands of the stack's own forward pass).
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass

import numpy as np

from torchcontact import spatial as sp
from torchcontact.onnx.builder import OPSET, Operand, bilinear, inline, onnx_type
from torchcontact.onnx.format import Key, decode, selection
from torchcontact.onnx.step.context import StepContext
from torchcontact.onnx.step.forms import (
    TP_ONE,
    force_to_child,
    signed,
    split,
    tp,
)

__all__ = [
    "NativeStack",
    "Wiring",
    "feature_entries",
    "fold_affine_ends",
    "native_corrections",
    "native_stack",
]


class Wiring:
    """How the single-frame graph feeds correction graphs from its packed input ``x``."""

    def __init__(self, ctx: StepContext, x: str) -> None:
        self.ctx, self.x = ctx, x
        self.states: list[tuple[str, tuple[int, ...], str]] = []
        #: the cosines of the affine entries, ``(1, E)`` (:meth:`angles`), and per native stack
        #: the ``(cos, sin)`` entries of its angle features (:func:`feature_entries`)
        self.cos_e: str | None = None
        self.n_entries = 0
        self.angle_entries: dict[int, list[tuple[int, int]]] = {}

    def angles(self, ce: str, n_entries: int) -> None:
        """Give the learned layers the cosines of the affine entries ``ce`` (a ``(1, E)`` row).

        The kinematics computes them (poses); the angle features are entries of them
        (:func:`feature_entries`), so no ``Sin``/``Cos`` of their own.
        """
        self.cos_e, self.n_entries = ce, n_entries

    def position(self, kind: str, key: str) -> int:
        """The column of ``x`` of ``("q" | "qd" | "qdd", joint)`` or ``("extra", name)``."""
        lay = self.ctx.lay
        if kind == "extra":
            return lay.index("extra", self.ctx.extra.index(key))
        return lay.index(kind, self.ctx.full.model.joint_names.index(key))

    def select(self, cols) -> str:
        """Columns ``("q" | "qd" | "qdd", joint)`` or ``("extra", name)`` of ``x``, ``(1, n)``."""

        def position(kind: str, key: str) -> int:
            return self.position(kind, key)

        position.size = self.ctx.lay.size  # type: ignore[attr-defined]
        return self.ctx.gb.op("MatMul", self.x, self.ctx.gb.f(selection(cols, position)))

    def state_in(self, rg, to: int) -> str:
        """The recurrent state ``h_in.<sensor>`` of ``x``, ``(1, L, H)`` of type ``to``."""
        gb, lay = self.ctx.gb, self.ctx.lay
        L, H = rg.state_shape
        start, stop, _ = lay.span(f"h_in.{rg.sensor}")
        sel = np.zeros((lay.size, L * H))
        sel[start:stop, :] = np.eye(L * H)
        h = gb.op("Reshape", gb.op("MatMul", self.x, gb.f(sel)), gb.i([1, L, H]))
        return gb.op("Cast", h, to=to)

    def state_out(self, rg, h: str) -> None:
        """Record a recurrent correction's next state (an output of the graph)."""
        L, H = rg.state_shape
        flat = self.ctx.gb.op("Reshape", self.ctx.gb.cast(h), self.ctx.gb.i([1, L * H]))
        self.states.append((rg.sensor, (L, H), flat))

    def project(self, sensor: str) -> np.ndarray:
        """``(6, F)``: a sensor's correction onto its reading's entries of ``x``."""
        lay = self.ctx.lay
        P = np.zeros((6, lay.size))
        s = list(self.ctx.em.sensor_names).index(sensor)
        for i in range(6):
            P[i, lay.index("ft", s, i)] = 1.0
        return P


@dataclass(frozen=True)
class NativeStack:
    """A correction stack the graph computes itself.

    Attributes:
        region: index of the corrected sensor's region.
        subtree: the sensor's subtree as body indices of the pruned tree.
        offset: ``(6,)`` or None.
        delta: pruned body index -> ``(m, h, I_origin)`` of the inertial layer, internal frame.
        columns: per selected input column ``("q" | "qd" | "qdd", joint)`` or ``("extra", name)``.
        sincos: the first ``n_angles`` columns enter as ``sin, cos`` pairs.
        n_angles: number of angle columns.
        perm: ``(V, F)`` 0/1 matrix from ``[sin, cos, other columns, nominal]`` to feature order.
        nominal: the features include the nominal wrench.
        learned: the learned layer's ``onnx.ModelProto`` or None.
    """

    region: int
    subtree: list[int]
    offset: np.ndarray | None
    delta: dict
    columns: list
    sincos: bool
    n_angles: int
    perm: np.ndarray | None
    nominal: bool
    learned: object


def native_stack(ctx: StepContext, rg, model) -> NativeStack | None:
    """The parts of a correction stack for a native build, or None (the graph is then inlined).

    Native when the graph carries its layers (``stack`` metadata), its sensor is one of the
    graph's regions, every body of the sensor's subtree is in the pruned tree, and no feature
    mixes prismatic angles into a sin/cos set. In an online graph the offset and inertial layers
    are the defaults of its ``bias`` and ``theta`` inputs
    (:func:`torchcontact.onnx.step.online.stack_defaults`): only the learned layer is built.

    Raises:
        InputError: an online graph with a stack that cannot be built natively (its offset and
            inertial layers would be applied twice).
    """
    import onnx
    from onnx import version_converter

    from torchcontact.residual import CorrectionSpec

    meta = decode({m.key: m.value for m in model.metadata_props})
    em, full = ctx.em, ctx.full
    if Key.STACK not in meta or rg.sensor not in em.sensor_names:
        return None
    spec = CorrectionSpec.from_json(meta[Key.STACK])
    region = list(em.sensor_names).index(rg.sensor)
    keep = list(ctx.keep)
    sub = full.model.subtree(keep[em.regions[region].child])
    if not set(sub) <= set(keep):
        return _not_native(ctx, rg)
    new = {old: k for k, old in enumerate(keep)}
    body_names = list(full.model.body_names)
    delta = {}
    for name, params in spec.inertial:
        i = body_names.index(name)
        m, hx, hy, hz, ixx, ixy, iyy, ixz, iyz, izz = params
        Q = np.asarray(full.tree.bodies[i].Q, float)  # R_link_internal
        Io = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        delta[new[i]] = (float(m), Q.T @ np.array([hx, hy, hz]), Q.T @ Io @ Q)
    columns, n_angles, sincos, perm, nominal, learned = [], 0, False, None, False, None
    if spec.learned is not None:
        cols = spec.columns(full.model)
        if cols is None:  # prismatic angles inside a sin/cos set
            return _not_native(ctx, rg)
        columns, n_angles, perm = cols
        sincos, nominal = n_angles > 0, spec.nominal
        learned = onnx.load_from_string(base64.b64decode(meta[Key.LEARNED_GRAPH]))
        version = next(o.version for o in learned.opset_import if o.domain in ("", "ai.onnx"))
        if version != OPSET:
            learned = version_converter.convert_version(learned, OPSET)
    if ctx.online:  # the offset and inertial layers are the online inputs' defaults
        return NativeStack(region, [new[i] for i in sub], None, {}, columns, sincos, n_angles,
                           perm, nominal, learned)  # fmt: skip
    return NativeStack(region, [new[i] for i in sub], spec.offset_array(), delta, columns,
                       sincos, n_angles, perm, nominal, learned)  # fmt: skip


def _not_native(ctx: StepContext, rg) -> None:
    if ctx.online:
        from torchcontact.errors import InputError

        raise InputError(
            f"online: the correction stack of {rg.sensor!r} ({rg.path}) cannot be built in the"
            " step graph, so its offset and inertial layers cannot become the online inputs;"
            " export without --online"
        )
    return None


def feature_entries(ctx: StepContext, wiring: Wiring, stacks: dict, ea) -> None:
    """Register the learned layers' angle features as entries of the affine plan.

    ``cos q`` is the entry ``q``, ``sin q`` the entry ``q - pi/2`` (the poses' own trick): the
    pose stage's one ``Cos`` of every entry then holds them, and the features of a stack are one
    ``Concat`` of those cosines, ``x`` and the nominal wrench, whose selection folds into the
    learned layer's first ``Gemm`` (:func:`_learned`).

    Args:
        ctx: the graph.
        wiring: where the entries are recorded (``angle_entries``).
        stacks: ``{r: (ResidualGraph, NativeStack)}``.
        ea: the affine plan (:func:`torchcontact.onnx.step.inputs.plan`), before ``check``.
    """
    for r, (_rg, st) in stacks.items():
        if st.learned is None or not st.sincos:
            continue
        ent = []
        for kind, key in st.columns[: st.n_angles]:
            j = wiring.position(kind, key)
            ent.append((ea.entry({j: 1.0}), ea.entry({j: 1.0}, -math.pi / 2)))
        wiring.angle_entries[r] = ent


def native_corrections(
    ctx, wiring: Wiring, stacks, TP, VAb, f0, F: str | None = None
) -> tuple[list[tuple[int, str]], list[tuple[np.ndarray, str]]]:
    """The native stacks' corrections ``c`` per region, and the terms of ``ws_corr``.

    A correction ``c`` (sensor frame and measure direction) is subtracted twice over: from the
    region's ``b`` (``sign c``, sensor frame: ``ws_corr = sum_terms col c``, ``(S, 6)``, with
    ``col`` the ``(S, 1)`` column holding the region's sign in its row; left as terms so that
    each is one ``Gemm`` where it is used) and from the wrench the reading transmits towards the
    root (the returned ``(region, c)``, for
    :func:`~torchcontact.onnx.step.kinematics.readings_root`). Its inertial layer ``Y delta`` is
    the subtree's Newton-Euler wrenches with the parameter change ``delta`` as inertias (the
    columns of ``F`` after the nominal ones, in the order of ``stacks`` that have one), summed
    and moved to the sensor frame; the nominal-wrench feature is the same with the nominal body
    wrenches ``f0``.

    Args:
        ctx: the graph.
        wiring: the input wiring (selections, recurrent states).
        stacks: ``{r: (ResidualGraph, NativeStack)}``.
        TP: pose features.
        VAb: ``[v, a, 1]`` in each body frame.
        f0: body wrenches, root frame, ``(nb, 6)``.
        F: ``[f0, f_delta...]`` (:func:`~torchcontact.onnx.step.kinematics.body_wrenches` with
            the stacks' ``delta``), or None when no stack has one.
    """
    gb, nb, S = ctx.gb, ctx.nb, ctx.S
    cres, terms = [], []
    n_delta = sum(1 for _rg, st in stacks.values() if st.delta)
    j = 0  # the next inertial change's block of F
    for r, (rg, st) in stacks.items():
        reg = ctx.em.regions[st.region]
        pick = gb.f(np.isin(np.arange(nb), st.subtree)[None, :].astype(float))
        blocks = ([0] if st.nominal else []) + ([1 + j] if st.delta else [])
        j += bool(st.delta)
        ws, k = None, len(blocks)
        if blocks:
            # root-frame subtree sums of the nominal and changed wrenches, one row
            if st.delta:
                sums, width = gb.op("MatMul", pick, F), 6 * (1 + n_delta)
            else:
                sums, width = gb.op("MatMul", pick, f0), 6

            # in the sensor frame, [nominal, changed] as one row (the stages below are products
            # of pose features and wrench entries only: the operands need no 1 column)
            def to_sensor(_i, t: list, w: list, reg=reg, blocks=blocks) -> list:
                R, _, pR, _ = tp(t)
                out = []
                for bl in blocks:
                    f = force_to_child(R, pR, split(w[6 * bl : 6 * bl + 6]))
                    f = signed(reg.sign, sp.force_to_child(reg.T_child_sensor, f))
                    out += [*f[0], *f[1]]
                return out

            ws = bilinear(gb, Operand(TP, 25, "nd", one=TP_ONE, row_of=[reg.child]),
                          Operand(sums, width), 1, to_sensor, 6 * k, one=False,
                          hint=f"ysum{r}")  # fmt: skip
        # the offset goes into the learned layer's last bias when that computes in this dtype
        shift = st.offset if np.dtype(rg.dtype) == ctx.dtype else None
        c, shifted = None, False
        if st.learned is not None:  # its nominal-wrench feature: the first 6 columns of ws
            c, shifted = _learned(ctx, wiring, (ws, 6 * k) if st.nominal else None, r, rg, st,
                                  shift)  # fmt: skip
        if st.offset is not None and not shifted:
            off = gb.f(st.offset[None, :])
            c = off if c is None else gb.op("Add", c, off)
        if st.delta:  # plus the inertial layer, the last 6 columns of ws
            last = np.zeros((6 * k, 6))
            last[6 * (k - 1) :, :] = np.eye(6)
            c = gb.op("MatMul", ws, gb.f(last)) if c is None else gb.op("Gemm", ws, gb.f(last), c)
        if c is None:
            continue
        col = np.zeros((S, 1))
        col[st.region, 0] = reg.sign
        terms.append((col, c))
        cres.append((st.region, c))
    return cres, terms


def _learned(ctx: StepContext, wiring: Wiring, nominal, r: int, rg, st: NativeStack,
             shift: np.ndarray | None = None) -> tuple[str, bool]:  # fmt: skip
    """The learned layer's output ``(1, 6)`` (graph dtype) on features built from ``x``.

    The raw features ``v = [sin q, cos q, other columns, nominal]`` are ``u S`` with
    ``u = [cos e, x, nominal]`` (one ``Concat``; ``cos e`` the row of the poses' cosines of
    every affine entry, which holds the angles' sin and cos, :func:`feature_entries`) and a
    constant 0/1 ``S``; ``S`` and the feature order
    ``perm`` fold into the first ``Gemm`` (:func:`fold_affine_ends`). ``x`` enters whole, as the
    column selection did before (a non-finite entry of ``x`` reaches the output, and the status).

    ``nominal``: ``(value, width)``, a row whose first 6 columns are the nominal wrench in the
    sensor frame, or None. Returns ``(output, shifted)``: whether ``shift`` (a constant ``(6,)``
    to add) is in it (folded into its last bias).
    """
    gb = ctx.gb
    to = onnx_type(rg.dtype)
    same = np.dtype(rg.dtype) == ctx.dtype
    na = st.n_angles if st.sincos else 0
    rest = st.columns[na:]
    F = ctx.lay.size
    nom, n_nom = nominal if nominal is not None else (None, 0)
    # the angles' [sin, cos]: entries of the row of the entries' cosines, which enters whole
    # (its selection folds into the first Gemm: no Gather)
    ents = wiring.angle_entries.get(r, [])
    trig = [s_ for _c, s_ in ents] + [c for c, _s in ents]
    parts, rows, offsets = [], 0, {}
    for name, value, width, used in (("trig", wiring.cos_e, wiring.n_entries, na > 0),
                                     ("x", wiring.x, F, bool(rest)),
                                     ("nominal", nom, n_nom, bool(st.nominal))):  # fmt: skip
        if used:
            parts.append(value)
            offsets[name] = rows
            rows += width
    V = 2 * na + len(rest) + 6 * bool(st.nominal)
    S = np.zeros((rows, V))
    if na:  # sin q = cos(q - pi/2), cos q
        S[offsets["trig"] + np.array(trig), np.arange(2 * na)] = 1.0
    for j, (kind, key) in enumerate(rest):
        S[offsets["x"] + wiring.position(kind, key), 2 * na + j] = 1.0
    if st.nominal:
        S[offsets["nominal"] : offsets["nominal"] + 6, V - 6 :] = np.eye(6)
    pre = S if st.perm is None else S @ np.asarray(st.perm, np.float64)
    u = parts[0] if len(parts) == 1 else gb.op("Concat", *parts, axis=1)
    learned, folded, shifted = fold_affine_ends(st.learned, pre, shift)
    feats = u if folded else gb.op("MatMul", u, gb.f(pre))
    feeds = {"features": feats if same else gb.op("Cast", feats, to=to)}
    if rg.state_shape:
        feeds["h_in"] = wiring.state_in(rg, to)
    outs = inline(gb, learned, f"res{r}/", feeds)
    if rg.state_shape:
        wiring.state_out(rg, outs["h_out"])
    return (outs["residual"] if same else gb.cast(outs["residual"])), shifted


def fold_affine_ends(model, pre: np.ndarray | None = None, shift: np.ndarray | None = None):
    """A learned layer's graph with its constant affine ends folded into its first and last layer.

    :func:`torchcontact.onnx.networks.emit_learned` writes ``z = (x - mean) / std`` before the
    first ``Gemm`` and ``y tstd + tmean`` after the last: on one frame each is a node of its own
    (onnxruntime's cost is per node). With ``pre`` (``(V, F)``, the features ``x = v pre``) the
    first three become one ``Gemm`` on ``v``: ``v (pre W / std) + (b - (mean / std) W)``; the last
    three one ``Gemm`` with ``W tstd`` and ``b tstd + tmean`` (``+ shift``). Other graphs (a GRU's
    first layer, another network) keep what does not match.

    Args:
        model: the learned layer's ``onnx.ModelProto`` (input ``features``).
        pre: ``(V, F)`` the map from the graph's values to the features, or None.
        shift: ``(6,)`` a constant to add to the output (the stack's offset), or None.

    Returns:
        ``(model, folded, shifted)``: a new model (or ``model`` itself), whether its input is now
        ``v`` (``pre`` folded in), whether its output includes ``shift``.
    """
    from onnx import helper, numpy_helper

    g = model.graph
    consts = {t.name: numpy_helper.to_array(t).astype(np.float64) for t in g.initializer}
    dtype = {t.name: numpy_helper.to_array(t).dtype for t in g.initializer}
    users: dict[str, list] = {}
    for n in g.node:
        for i in n.input:
            users.setdefault(i, []).append(n)
    producer = {o: n for n in g.node for o in n.output}

    def only_user(value: str, op: str):
        us = users.get(value, [])
        ok = len(us) == 1 and us[0].op_type == op and all(i in consts for i in us[0].input[1:])
        return us[0] if ok else None

    def linear(n) -> tuple[np.ndarray, np.ndarray] | None:
        """``(W (in, out), b)`` of a plain ``Gemm``/``MatMul`` with constant weights."""
        attrs = {a.name: helper.get_attribute_value(a) for a in n.attribute}
        if n.op_type == "MatMul":
            W = consts[n.input[1]]
            return W, np.zeros(W.shape[1])
        if (
            attrs.get("transA", 0)
            or attrs.get("alpha", 1.0) != 1.0
            or attrs.get("beta", 1.0) != 1.0
        ):
            return None
        W = consts[n.input[1]].T if attrs.get("transB", 0) else consts[n.input[1]]
        b = consts[n.input[2]] if len(n.input) > 2 else np.zeros(W.shape[1])
        return W, np.broadcast_to(b, (W.shape[1],)).astype(np.float64)

    drop, add, inits = set(), {}, []
    kind = dtype[next(iter(consts))] if consts else np.float32

    def gemm(x: str, W: np.ndarray, b: np.ndarray, out: str, tag: str):
        names = [f"folded_{tag}_W", f"folded_{tag}_b"]
        inits.extend([numpy_helper.from_array(W.astype(kind), names[0]),
                      numpy_helper.from_array(b.astype(kind), names[1])])  # fmt: skip
        return helper.make_node("Gemm", [x, *names], [out], name=out)

    folded = shifted = False
    sub = only_user("features", "Sub") if pre is not None else None
    div = sub and only_user(sub.output[0], "Div")
    first = div and (only_user(div.output[0], "Gemm") or only_user(div.output[0], "MatMul"))
    if first is not None and (wb := linear(first)) is not None:
        mean, std = consts[sub.input[1]], consts[div.input[1]]
        W, b = wb
        Wn = np.asarray(pre, np.float64) @ (W / std.reshape(-1, 1))
        bn = b - (mean / std).reshape(-1) @ W
        add[first.name or first.output[0]] = gemm("features", Wn, bn, first.output[0], "in")
        drop |= {id(sub), id(div), id(first)}
        folded = True
    out = g.output[0].name
    last_add = producer.get(out)
    if last_add is not None and last_add.op_type == "Identity":
        last_add = producer.get(last_add.input[0])
    mul = (
        producer.get(last_add.input[0])
        if last_add is not None and last_add.op_type == "Add"
        else None
    )
    last = producer.get(mul.input[0]) if mul is not None and mul.op_type == "Mul" else None
    if (last is not None and last_add.input[1] in consts and mul.input[1] in consts
            and last.op_type in ("Gemm", "MatMul") and id(last) not in drop
            and len(users.get(last.output[0], [])) == 1 and len(users.get(mul.output[0], [])) == 1
            and all(i in consts for i in last.input[1:])
            and (wb := linear(last)) is not None):  # fmt: skip
        scale, add_ = consts[mul.input[1]].reshape(-1), consts[last_add.input[1]].reshape(-1)
        W, b = wb
        bias = b * scale + add_ + (0.0 if shift is None else np.asarray(shift, np.float64))
        add[last.name or last.output[0]] = gemm(last.input[0], W * scale, bias,
                                                last_add.output[0], "out")  # fmt: skip
        shifted = shift is not None
        drop |= {id(mul), id(last_add), id(last)}
    if not drop:
        return model, False, False
    nodes = []
    for n in g.node:
        if id(n) in drop:
            key = n.name or n.output[0]
            if key in add:
                nodes.append(add[key])
            continue
        nodes.append(n)
    inputs = list(g.input)
    if folded:
        x = next(i for i in inputs if i.name == "features")
        shape = [d.dim_param or d.dim_value for d in x.type.tensor_type.shape.dim]
        new_x = helper.make_tensor_value_info("features", x.type.tensor_type.elem_type,
                                              [shape[0], int(np.shape(pre)[0])])  # fmt: skip
        inputs = [new_x if i.name == "features" else i for i in inputs]
    used = {i for n in nodes for i in n.input}
    kept = [t for t in g.initializer if t.name in used]
    graph = helper.make_graph(nodes, g.name, inputs, list(g.output), initializer=kept + inits)
    new = helper.make_model(graph, opset_imports=list(model.opset_import))
    new.ir_version = model.ir_version
    return new, folded, shifted
