"""The online stage of the single-frame graph: offsets and payloads in, the model's reading out.

A step graph exported with ``online`` (``export estimator --online``) takes per sensor its offset
and its inertial change as inputs and returns what a bias tracker and a payload identification
need (:mod:`torchcontact.online`), the same interface as the C step
(:mod:`torchcontact.online.cstep`):

* inputs ``bias`` ``(S, 6)``, subtracted from the readings (in the input stage's affine entries:
  no node), and ``theta.<sensor>`` ``(10 B,)``, the inertial change of the ``B`` bodies of the
  sensor's subtree (ten parameters per body, link frame, about the body origin,
  :data:`~torchcontact.online.payload.PARAM_NAMES`; the correction stack's inertial layer plus
  the payload), whose wrench ``Y theta`` is subtracted from the reading;
* outputs ``ft_model`` ``(S, 6)``, the contact-free reading the model predicts (the nominal
  subtree wrench plus ``Y theta``, plus the learned and chained corrections: everything but the
  offset), and ``regressor.<sensor>`` ``(6, 10)``, the sensor regressor of its payload body.

The regressor ``Y`` (Atkeson, An and Hollerbach 1986;
:func:`torchcontact.residual.sensor_regressor`) is built on this graph's own forward pass: per
subtree body, the Newton-Euler wrench of each unit parameter
(:func:`torchcontact.spatial.body_wrench_link_params`) in the body frame, moved to the root
frame, weighted by ``theta`` and summed per sensor; the sums, the nominal subtree wrench and the
payload body's columns go to the sensor frames in one stage. About 25 nodes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from torchcontact import spatial as sp
from torchcontact.onnx.builder import Operand, bilinear
from torchcontact.onnx.format import Key, decode
from torchcontact.onnx.step.context import StepContext
from torchcontact.onnx.step.forms import (
    TP_ONE,
    force_to_child,
    force_to_parent,
    signed,
    split,
    tp,
)

__all__ = ["OnlineTerms", "fields", "model_terms", "rows", "stack_defaults"]

#: Parameters per body (:data:`torchcontact.online.payload.PARAM_NAMES`).
P = 10


def fields(ctx: StepContext) -> list[tuple[str, tuple[int, ...]]]:
    """The online inputs of the packed vector: ``bias (S, 6)``, ``theta.<sensor> (10 B,)``."""
    if not ctx.online:
        return []
    return [("bias", (ctx.S, 6))] + [
        (f"theta.{lay.name}", (P * len(lay.bodies),)) for lay in ctx.online
    ]


def rows(ctx: StepContext) -> list[tuple[int, int]]:
    """``(sensor, pruned body)`` of every subtree body, in ``theta``'s order.

    Raises:
        InputError: a subtree body the pruned graph does not keep.
    """
    from torchcontact.errors import InputError

    keep = {old: k for k, old in enumerate(ctx.keep)}
    out = []
    for i, lay in enumerate(ctx.online):
        missing = [b for b in lay.bodies if b not in keep]
        if missing:
            names = [ctx.full.model.body_names[b] for b in missing]
            raise InputError(f"online: bodies {names} of sensor {lay.name!r} are not in the graph")
        out += [(i, keep[b]) for b in lay.bodies]
    return out


def stack_defaults(model, residuals: Sequence, sensors: Sequence[str]) -> tuple[dict, dict]:
    """The ``theta.<sensor>`` and ``bias`` defaults of chained correction stacks.

    A stack that carries its layers (``stack`` metadata) gives its inertial layer, spread over
    the sensor's subtree (the C step's layout), and its offset; the graph then builds only its
    learned layer (:func:`~torchcontact.onnx.step.corrections.native_stack`).

    Args:
        model: the robot.
        residuals: ``[(ResidualGraph, onnx.ModelProto)]``.
        sensors: the estimator's sensors.

    Returns:
        ``(theta0, offsets)``: sensor -> ``(10 B,)``, sensor -> ``(6,)``.
    """
    from torchcontact.residual import CorrectionSpec

    theta0, offsets = {}, {}
    for rg, mp in residuals:
        meta = decode({m.key: m.value for m in mp.metadata_props})
        if Key.STACK not in meta or rg.sensor not in sensors:
            continue
        spec = CorrectionSpec.from_json(meta[Key.STACK])
        if spec.offset is not None:
            offsets[rg.sensor] = spec.offset_array()
        if spec.inertial:
            bodies = model.subtree(model.ft_sensors[rg.sensor].child_body)
            th = np.zeros(P * len(bodies))
            for name, params in spec.inertial:
                j = bodies.index(model.body_names.index(name))
                th[P * j : P * j + P] = params
            theta0[rg.sensor] = th
    return theta0, offsets


@dataclass(frozen=True)
class OnlineTerms:
    """The online stage's values.

    Attributes:
        ft_model: ``(S, 6)`` the model's contact-free reading with ``theta`` (sensor frames,
            reading sense); the stages add the learned and chained corrections.
        ws_corr: ``(S, 6)`` ``Y theta`` as subtracted from each region's ``b`` (signed).
        delta_root: ``(S, 6)`` the wrench of ``Y theta`` in the root frame (subtracted from the
            readings' wrenches that regions upstream see).
        regressors: ``(1, 60 S)`` per sensor the ``(6, 10)`` payload regressor, row-major.
    """

    ft_model: str
    ws_corr: str
    delta_root: str
    regressors: str


def model_terms(ctx: StepContext, e: str, idx: dict, TP: str, VAb: str, f0: str) -> OnlineTerms:
    """``ft_model``, ``Y theta`` and the payload regressors (see the module).

    Args:
        ctx: the graph (``ctx.online`` the sensors' layouts).
        e: the affine entries (``idx["theta"]``: ``theta``'s entries, cleaned of non-finite
            values).
        idx: their indices.
        TP: pose features.
        VAb: ``[v, a, 1]`` in each body frame.
        f0: nominal body wrenches, root frame.
    """
    gb, em, S = ctx.gb, ctx.em, ctx.S
    rws = rows(ctx)
    n = P * len(rws)
    body = [b for _, b in rws]

    # ---- the unit parameters' Newton-Euler wrenches of each subtree body, body frame
    def units(r: int, va: list, _b: list) -> list:
        Q = np.asarray(em.tree.bodies[body[r]].Q, float)
        v, a = split(va[0:6]), split(va[6:12])
        out: list = []
        for c in range(P):
            w = sp.body_wrench_link_params(Q, [1.0 if k == c else 0.0 for k in range(P)], v, a)
            out += [*w[0], *w[1]]
        return out

    Yb = bilinear(gb, Operand(VAb, 13, "nd", one=12, row_of=body), None, len(rws), units, 6 * P,
                  one=False, hint="ybody")  # fmt: skip
    Yb = gb.op("Reshape", Yb, gb.i([n, 6]))  # row (subtree body, parameter)

    # ---- to the root frame, about its origin
    def to_root(_r: int, t: list, f: list) -> list:
        R, _, pR, _ = tp(t)
        w = force_to_parent(R, pR, split(f[0:6]))
        return [*w[0], *w[1]]

    each = [b for b in body for _ in range(P)]
    Yroot = bilinear(gb, Operand(TP, 25, "nd", one=TP_ONE, row_of=each), Operand(Yb, 6), n,
                     to_root, 6, one=False, hint="yroot")  # fmt: skip
    # ---- Y theta per sensor (root frame), the nominal subtree wrench, the payload columns
    theta = gb.op("Gather", e, gb.i(np.array(idx["theta"])[:, None]), axis=0)  # (n, 1)
    sel = np.zeros((S, n))
    for k, (i, _) in enumerate(rws):
        sel[i, P * k : P * k + P] = 1.0
    delta_root = gb.op("MatMul", gb.f(sel), gb.op("Mul", Yroot, theta))
    pick = np.zeros((S, ctx.nb))
    for i, b in rws:
        pick[i, b] = 1.0
    model_root = gb.op("Gemm", gb.f(pick), f0, delta_root)
    pay = []
    for i, lay in enumerate(ctx.online):
        k = rws.index((i, {old: j for j, old in enumerate(ctx.keep)}[lay.payload_body]))
        pay += range(P * k, P * k + P)
    stacked = gb.op("Concat", model_root, delta_root,
                    gb.op("Gather", Yroot, gb.i(pay), axis=0), axis=0)  # fmt: skip

    # ---- to the sensor frames: the model's reading, Y theta for b, the regressor columns
    sensor_of = list(range(S)) + list(range(S)) + [i for i in range(S) for _ in range(P)]
    regs = em.regions

    def to_sensor(r: int, t: list, w: list) -> list:
        reg = regs[sensor_of[r]]
        R, _, pR, _ = tp(t)
        Fs = sp.force_to_child(reg.T_child_sensor, force_to_child(R, pR, split(w[0:6])))
        out = signed(1.0 if S <= r < 2 * S else reg.sign, Fs)  # b's correction: unsigned
        return [*out[0], *out[1]]

    sens = bilinear(gb, Operand(TP, 25, "nd", one=TP_ONE,
                                row_of=[regs[i].child for i in sensor_of]),
                    Operand(stacked, 6), len(sensor_of), to_sensor, 6, one=False,
                    hint="ysens")  # fmt: skip

    def part(a: int, b: int) -> str:
        return gb.op("Slice", sens, gb.i([a]), gb.i([b]), gb.i([0]))

    reg_cols = gb.op("Reshape", part(2 * S, 12 * S), gb.i([S, P, 6]))  # (sensor, column, row)
    flat = gb.op("Reshape", gb.op("Transpose", reg_cols, perm=[0, 2, 1]), gb.i([1, 6 * P * S]))
    return OnlineTerms(part(0, S), part(S, 2 * S), delta_root, flat)
