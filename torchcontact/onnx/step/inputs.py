"""Stage 1 of the single-frame graph: the packed input, its checks and the status bits.

The graph takes one vector ``x (1, F)`` (fields and offsets in :class:`StepLayout`, written to
the metadata). Non-finite entries are flagged (status bits of :class:`torchcontact.Status`, as
:func:`torchcontact.estimation.programs.estimate_program` sets them) and zeroed; every affine
function of the inputs the later stages need (joint angles and rates per body, readings in the
sensors' child frames, contact points in their bodies' frames, ...) is one ``Gemm``: the vector
``e = x M + off`` (:class:`Affine`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from torchcontact import spatial as sp
from torchcontact.onnx import format as fmt
from torchcontact.onnx.step.context import StepContext
from torchcontact.onnx.step.forms import const_force_map
from torchcontact.status import Status

__all__ = ["Affine", "Checked", "check", "fields", "plan"]


def fields(em, flags, extra: Sequence[str], states: Sequence[tuple[str, tuple[int, ...]]]):
    """The packed input's fields ``[(name, shape)]`` of a layout, in order.

    Args:
        em: the layout.
        flags: the optional inputs (:class:`~torchcontact.onnx.step.context.Flags`).
        extra: the extra columns of chained corrections.
        states: ``(sensor, (L, H))`` of chained recurrent corrections.
    """
    nv, S, K = em.tree.nv, len(em.regions), len(em.slots)
    out = [("q", (nv,)), ("qd", (nv,)), ("qdd", (nv,)), ("ft", (S, 6)), ("ft_residual", (S, 6)),
           ("positions", (K, 3)), ("active", (K,))]  # fmt: skip
    if "force_dir" in em.kinds:
        out.append(("directions", (K, 3)))
    if "known" in em.kinds:
        out.append(("wrenches", (K, 6)))
    if flags.moving_base:
        out += [(name, (3,)) for name in fmt.BASE_INPUTS]
    if flags.torque_rows:
        out += [(name, (nv,)) for name in fmt.TORQUE_INPUTS]
    if flags.covariance:
        out.append((fmt.COVARIANCE_INPUT, (S, 6, 6)))
    if extra or states:
        out.append((fmt.EXTRA, (len(extra),)))
        out += [(fmt.state_in(s), tuple(shape)) for s, shape in states]
    return out


class Affine:
    """The vector ``e = x M + off``: every affine function of the inputs the graph uses."""

    def __init__(self, n_in: int) -> None:
        self.n_in = n_in
        self.cols: list[np.ndarray] = []
        self.off: list[float] = []
        self._seen: dict = {}
        self.one = self.entry({}, 1.0)
        self.zero = self.entry({}, 0.0)

    def entry(self, coef: dict[int, float], off: float = 0.0) -> int:
        """Index of the entry ``sum coef[i] x[i] + off`` (deduplicated)."""
        coef = {int(i): float(c) for i, c in coef.items() if c != 0.0}
        key = (tuple(sorted(coef.items())), float(off))
        if key not in self._seen:
            col = np.zeros(self.n_in)
            for i, c in coef.items():
                col[i] += c
            self._seen[key] = len(self.cols)
            self.cols.append(col)
            self.off.append(float(off))
        return self._seen[key]

    def value(self, k: int) -> float:
        """The value of a constant entry."""
        if np.any(self.cols[k]):
            raise ValueError("not a constant entry")
        return self.off[k]

    def matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """``(M, off)``: ``(F, E)`` and ``(1, E)``."""
        return np.stack(self.cols, 1), np.array(self.off)[None, :]


def _combine(weights: np.ndarray, rows: list[dict]) -> dict:
    out: dict = {}
    for w, r in zip(weights, rows, strict=True):
        for i, c in r.items():
            out[i] = out.get(i, 0.0) + float(w) * c
    return out


def plan(ctx: StepContext) -> tuple[Affine, dict]:
    """Register the entries of ``e``; returns the plan and their indices by purpose.

    Keys: ``cos, sin, disp, qd, qdd`` (per body), ``base`` (``[v0; a0; 1]``), ``W_s``, ``W_c``
    (per sensor: its wrench on the region in the sensor frame, and in the child body frame),
    ``pos_b, act, dir, wrench`` (per slot), ``tau_meas, tau_mask``, ``cov``, ``lim_pos, lims``.
    """
    em, lay, tree = ctx.em, ctx.lay, ctx.em.tree
    ea = Affine(lay.size)
    idx: dict = {}
    q0, qd0, qdd0 = (lay.fields[k][0] for k in ("q", "qd", "qdd"))
    # joint angles (cos and sin through cos(theta - pi/2)), displacements, rates per body
    cos_i, sin_i, disp_i, qd_i, qdd_i = [], [], [], [], []
    for b in tree.bodies:
        if b.kind == "revolute":
            cos_i.append(ea.entry({q0 + b.coord: b.mult}, b.offset))
            sin_i.append(ea.entry({q0 + b.coord: b.mult}, b.offset - math.pi / 2))
        else:
            cos_i.append(ea.zero)
            sin_i.append(ea.zero)
        disp_i.append(
            ea.entry({q0 + b.coord: b.mult}, b.offset) if b.kind == "prismatic" else ea.zero
        )
        moving = b.coord >= 0
        qd_i.append(ea.entry({qd0 + b.coord: b.mult}) if moving else ea.zero)
        qdd_i.append(ea.entry({qdd0 + b.coord: b.mult}) if moving else ea.zero)
    idx.update(cos=cos_i, sin=sin_i, disp=disp_i, qd=qd_i, qdd=qdd_i)
    # base motion: v0 = [0; omega], a0 = [proper_acc; domega] (fixed base: a0 = [-g; 0])
    if ctx.flags.moving_base:
        om, dom, acc = (lay.fields[k][0] for k in fmt.BASE_INPUTS)
        v0 = [ea.zero] * 3 + [ea.entry({om + i: 1.0}) for i in range(3)]
        a0 = [ea.entry({acc + i: 1.0}) for i in range(3)]
        a0 += [ea.entry({dom + i: 1.0}) for i in range(3)]
    else:
        v0 = [ea.zero] * 6
        a0 = [ea.entry({}, -float(g)) for g in tree.gravity] + [ea.zero] * 3
    idx["base"] = v0 + a0 + [ea.one]
    # readings: corrected r = ft - ft_residual [- bias] in the sensor frame; W = sign r (the
    # wrench the parent side exerts on the region, sensor frame), W_c = W in the child body frame
    W_s, W_c = [], []
    online = "bias" in lay.fields  # the offsets are inputs too (online graphs)
    for s, reg in enumerate(em.regions):
        rows = [
            {lay.index("ft", s, i): reg.sign, lay.index("ft_residual", s, i): -reg.sign}
            | ({lay.index("bias", s, i): -reg.sign} if online else {})
            for i in range(6)
        ]
        W_s.append([ea.entry(r) for r in rows])
        Ad = const_force_map(lambda f, T=reg.T_child_sensor: sp.force_to_parent(T, f))
        W_c.append([ea.entry(_combine(Ad[o], rows)) for o in range(6)] + [ea.one])
    idx.update(W_s=W_s, W_c=W_c)
    # the inertial changes of online graphs, in theta's order
    idx["theta"] = [ea.entry({o + j: 1.0}) for name, (o, shape) in lay.fields.items()
                    if name.startswith("theta.") for j in range(shape[0])]  # fmt: skip
    # contact points in the slot body's internal frame, activity, directions, wrenches
    pos_b, acts, dirs, wr = [], [], [], []
    for k, slot in enumerate(em.slots):
        R, p = np.array(slot.R, dtype=float), np.array(slot.p, dtype=float)
        pos_b.append(
            [ea.entry({lay.index("positions", k, j): R[i, j] for j in range(3)}, p[i])
             for i in range(3)] + [ea.one]
        )  # fmt: skip
        acts.append(ea.entry({lay.index("active", k): 1.0}))
        if "directions" in lay.fields:
            dirs.append([ea.entry({lay.index("directions", k, i): 1.0}) for i in range(3)])
        if "wrenches" in lay.fields:
            wr.append([ea.entry({lay.index("wrenches", k, i): 1.0}) for i in range(6)])
    idx.update(pos_b=pos_b, act=acts, dir=dirs, wrench=wr)
    if ctx.flags.torque_rows:
        t0, m0 = (lay.fields[k][0] for k in fmt.TORQUE_INPUTS)
        idx["tau_meas"] = [ea.entry({t0 + c: 1.0}) for c in range(ctx.nv)]
        idx["tau_mask"] = [ea.entry({m0 + c: 1.0}) for c in range(ctx.nv)]
    if ctx.flags.covariance:
        c0 = lay.fields[fmt.COVARIANCE_INPUT][0]
        idx["cov"] = [[ea.entry({c0 + 36 * s + i: 1.0}) for i in range(36)] for s in range(ctx.S)]
    # implausible values: |qd| beyond the velocity limits, readings beyond the sensor ranges
    lim_pos, lims = [], []
    if em.velocity_limit is not None:
        for c, v in enumerate(em.velocity_limit):
            if v != float("inf"):
                lim_pos.append(ea.entry({qd0 + c: 1.0}))
                lims.append(v)
    for s, rng in enumerate(em.ft_range):
        if rng is not None:
            lim_pos += W_s[s]
            lims += list(rng)
    idx.update(lim_pos=lim_pos, lims=lims)
    return ea, idx


@dataclass(frozen=True)
class Checked:
    """The checked input.

    Attributes:
        e: the affine entries ``(E,)`` of the cleaned input (non-finite entries zeroed).
        e_row: the same as a ``(1, E)`` row (the ``Gemm``'s own output).
        act: ``(K [+ nv], 1)`` 0/1 slot activity [and torque-mask validity].
        actK: ``(K, 1)`` slot activity.
        status: ``(1, 1)`` float status bits of the inputs (0: ok).
    """

    e: str
    e_row: str
    act: str
    actK: str  # noqa: N815 - K slots
    status: str


def check(ctx: StepContext, x: str, ea: Affine, idx: dict) -> Checked:
    """Flag and zero non-finite entries of ``x``; the entries ``e``; the inputs' status bits."""
    gb = ctx.gb
    bad = gb.op("IsNaN", gb.op("Sub", x, x))  # x - x is NaN exactly for NaN and inf
    xc = gb.op("Where", bad, gb.f(0.0), x)
    M, off = ea.matrix()
    e_row = gb.op("Gemm", xc, gb.f(M), gb.f(off))
    e = gb.op("Reshape", e_row, gb.i([M.shape[1]]))
    act = _activity(ctx, e, idx)
    actK = (
        gb.op("Slice", act, gb.i([0]), gb.i([ctx.K]), gb.i([0])) if ctx.flags.torque_rows else act
    )
    return Checked(e, e_row, act, actK, _status(ctx, x, bad, act, e, idx))


def _activity(ctx: StepContext, e: str, idx: dict) -> str:
    """Slot activity (and torque-mask validity) as a ``(K [+ nv], 1)`` 0/1 column."""
    gb = ctx.gb
    pos = list(idx["act"]) + (list(idx["tau_mask"]) if ctx.flags.torque_rows else [])
    if not pos:
        return gb.f(np.zeros((0, 1)))
    a = gb.op("Gather", e, gb.i(np.array(pos)[:, None]), axis=0)
    return gb.cast(gb.op("Greater", a, gb.f(0.5)))


def _status(ctx: StepContext, x: str, bad: str, act: str, e: str, idx: dict) -> str:
    """The inputs' status bits (all but :attr:`Status.OUTPUT_NONFINITE`), ``(1, 1)`` float."""
    gb, lay, K = ctx.gb, ctx.lay, ctx.K
    F = lay.size
    # per input entry, the bit its non-finite value sets (counted, then clipped to one)
    bits = [Status.FT_NONFINITE, Status.JOINT_NONFINITE, Status.CONTACT_NONFINITE,
            Status.TORQUE_NONFINITE]  # fmt: skip
    Mb = np.zeros((F, len(bits)))
    for name in lay.fields:  # the readings and what corrects them
        if name in ("ft", "ft_residual", "bias") or name.startswith("theta."):
            start, stop, _ = lay.span(name)
            Mb[start:stop, 0] = 1.0
    for name in ("q", "qd", "qdd", *fmt.BASE_INPUTS):
        if name in lay.fields:
            start, stop, _ = lay.span(name)
            Mb[start:stop, 1] = 1.0
    # contact entries count only where their slot is active (torques only where measured)
    n_gate = K + (ctx.nv if ctx.flags.torque_rows else 0)
    gate = np.zeros((n_gate, F))
    ungated = np.ones((1, F))
    for k, kind in enumerate(ctx.kinds):
        names = ["positions"] + (["directions"] if kind == "force_dir" else [])
        names += ["wrenches"] if kind == "known" else []
        for name in names:
            for i in range(lay.fields[name][1][-1]):
                j = lay.index(name, k, i)
                Mb[j, 2] = 1.0
                gate[k, j] = 1.0
                ungated[0, j] = 0.0
    if ctx.flags.torque_rows:
        for c in range(ctx.nv):
            j = lay.index("tau_measured", c)
            Mb[j, 3] = 1.0
            gate[K + c, j] = 1.0
            ungated[0, j] = 0.0
    if n_gate:  # the gate where the entry is bad, else 0: one Where (no Cast, no Mul)
        g = gb.op("Gemm", act, gb.f(gate), gb.f(ungated), transA=1)
        badf = gb.op("Where", bad, g, gb.f(0.0))
    else:
        badf = gb.cast(bad)
    counts = gb.op("MatMul", badf, gb.f(Mb))
    parts = [counts]
    weights = [float(b) for b in bits]
    if "force_dir" in ctx.kinds:
        # an active force_dir slot whose (finite) direction has zero length
        kd = [k for k, kind in enumerate(ctx.kinds) if kind == "force_dir"]
        xf = gb.op("Reshape", x, gb.i([F]))
        where = [[lay.index("directions", k, i) for i in range(3)] for k in kd]
        d = gb.op("Gather", xf, gb.i(where), axis=0)
        n2 = gb.op("ReduceSumSquare", d, gb.i([1]), keepdims=1)
        zero = gb.cast(gb.op("Equal", n2, gb.f(0.0)))
        a = gb.op("Gather", act, gb.i(kd), axis=0)
        parts.append(gb.op("Transpose", gb.op("Mul", zero, a), perm=[1, 0]))
        weights += [float(Status.ZERO_DIRECTION)] * len(kd)
    allc = parts[0] if len(parts) == 1 else gb.op("Concat", *parts, axis=1)
    status = gb.op("MatMul", gb.op("Min", allc, gb.f(1.0)), gb.f(np.array(weights)[:, None]))
    # implausible values, only when nothing else is wrong
    lim_pos, lims = idx["lim_pos"], idx["lims"]
    if lim_pos:
        vals = gb.op("Abs", gb.op("Gather", e, gb.i(lim_pos), axis=0))
        over = gb.op("ReduceMax", gb.cast(gb.op("Greater", vals, gb.f(lims))), keepdims=1)
        clean = gb.cast(gb.op("Equal", status, gb.f(0.0)))
        implausible = gb.op("Mul", gb.op("Mul", over, clean), gb.f(float(Status.IMPLAUSIBLE)))
        status = gb.op("Add", status, implausible)
    return status
