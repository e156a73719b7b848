"""The batched estimator graphs and the one wiring of chained corrections.

* :func:`batched_graph`: the estimator program of :mod:`torchcontact.estimation.programs` emitted
  one node per scalar operation (:func:`~torchcontact.onnx.builder.emit_program`), each node
  running over the ``N`` frames (throughput);
* :func:`constrained_graph`: the friction-cone constrained program, its interior-point
  iterations one ONNX ``Loop`` (the graph holds one iteration, not the budget);
* :func:`chain_corrections`: correction graphs inlined in front of an estimator graph, fed from
  the joint state and extra columns. The batched and the single-frame graphs both chain through
  it; the runtime feeds separately chained graphs through the same column selector
  (:func:`torchcontact.onnx.format.selection`).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from torchcontact.estimation.layout import EstimationModel
from torchcontact.onnx import format as fmt
from torchcontact.onnx.builder import OPSET, GraphBuilder, emit_program, inline, onnx_type

__all__ = [
    "base_shapes",
    "batched_graph",
    "chain_corrections",
    "constrained_graph",
    "load_residual_graphs",
    "residual_meta",
]


def base_shapes(nv: int, S: int, K: int) -> dict[str, list]:
    """Shapes of the inputs every batched estimator graph takes (``N`` dynamic)."""
    shapes = {"q": [nv], "qd": [nv], "qdd": [nv], "ft": [S, 6], "positions": [K, 3],
              "directions": [K, 3], "wrenches": [K, 6], "active": [K],
              "ft_residual": [S, 6]}  # fmt: skip
    return {k: ["N", *shapes[k]] for k in fmt.ESTIMATOR_INPUTS}


def load_residual_graphs(residual, model, sensor_names: Sequence[str]) -> list:
    """Load and check the correction graphs to chain: ``[(ResidualGraph, ModelProto)]``.

    Raises:
        ModelMismatchError: a graph made for another robot, joints or sensor, or two for one
            sensor.
    """
    import onnx
    from onnx import version_converter

    from torchcontact.errors import ModelMismatchError
    from torchcontact.onnx.residuals import ResidualGraph

    if residual is None:
        return []
    paths = [residual] if isinstance(residual, (str, os.PathLike)) else list(residual)
    out = []
    for p in paths:
        rg = ResidualGraph.load(p)
        rg.check(model.joint_names, sensor_names, model)
        if any(r.sensor == rg.sensor for r, _ in out):
            raise ModelMismatchError(f"two residual graphs correct sensor {rg.sensor!r}")
        m = onnx.load(str(p))
        version = next(o.version for o in m.opset_import if o.domain in ("", "ai.onnx"))
        if version != OPSET:
            m = version_converter.convert_version(m, OPSET)
        del rg.session  # not needed at export
        out.append((rg, m))
    return out


def residual_meta(res: list) -> list[dict]:
    """The ``residuals`` metadata of chained corrections."""
    return [
        {
            "sensor": rg.sensor,
            "format": rg.format,
            "extra": list(rg.extra),
            "state_shape": list(rg.state_shape) if rg.state_shape else None,
            "file": Path(rg.path).name,
            "sha256": hashlib.sha256(Path(rg.path).read_bytes()).hexdigest(),
        }
        for rg, _ in res
    ]


def chain_corrections(
    gb: GraphBuilder,
    residuals: Sequence,
    select: Callable[[Sequence[tuple[str, str]]], str],
    state_in: Callable[[object, int], str],
    skip: set[int] = frozenset(),  # type: ignore[assignment]
) -> list[tuple[int, object, str, str | None]]:
    """Inline correction graphs, each fed from selected input columns (and its state).

    Args:
        gb: the graph.
        residuals: ``[(ResidualGraph, ModelProto)]``.
        select: columns ``[(kind, key)]`` -> a ``(n, len)`` value in the graph dtype.
        state_in: ``(ResidualGraph, onnx type) -> (n, L, H)`` value of its recurrent state.
        skip: indices of corrections built otherwise (native stacks).

    Returns:
        Per inlined correction ``(index, ResidualGraph, correction (n, 6) in the graph dtype,
        next state or None)``.
    """
    out = []
    for r, (rg, model) in enumerate(residuals):
        if r in skip:
            continue
        to = onnx_type(rg.dtype)
        feeds = {name: state_in(rg, to) if cols is None else gb.op("Cast", select(cols), to=to)
                 for name, cols in rg.inputs}  # fmt: skip
        o = inline(gb, model, f"res{r}/", feeds)
        h = o[rg.output_names[1]] if rg.state_shape else None
        out.append((r, rg, gb.cast(o[rg.output]), h))
    return out


def _program_inputs(gb: GraphBuilder, em: EstimationModel, readings: str) -> dict[str, str]:
    """The program's inputs from the graph's (the same names): readings and slot data flat."""
    K = len(em.slots)
    ins = {"q": "q", "qd": "qd", "qdd": "qdd", "active": "active", "ft": readings}
    for name, width in (("positions", 3), ("directions", 3), ("wrenches", 6)):
        ins[name] = gb.op("Reshape", name, gb.i([-1, width * K]))
    return ins


def _estimator_outputs(gb: GraphBuilder, cols: dict, K: int, nv: int, S: int, coords) -> None:
    """The estimator outputs (:data:`~torchcontact.onnx.format.ESTIMATOR_OUTPUTS`)."""
    i64 = onnx_type(np.int64)
    gb.op("Reshape", cols["force"], gb.i([-1, K, 3]), out="force")
    gb.op("Reshape", cols["moment"], gb.i([-1, K, 3]), out="moment")
    if len(coords) < nv:  # torques not asked for: NaN
        nan = np.full(nv, np.nan)
        nan[list(coords)] = 0.0
        gb.op("Add", cols["tau"], gb.f(nan), out="joint_torques")
    else:
        gb.op("Identity", cols["tau"], out="joint_torques")
    gb.op("Cast", cols["rank"], to=i64, out="rank")
    gb.op("Cast", cols["unknowns"], to=i64, out="unknowns")
    gb.op("Identity", cols["residual"], out="residual")
    gb.op("Cast", gb.op("Reshape", cols["status"], gb.i([-1])), to=i64, out="status")
    for name, sh in (("force", ["N", K, 3]), ("moment", ["N", K, 3]), ("joint_torques", ["N", nv])):
        gb.output(name, sh)
    for name in ("rank", "unknowns"):
        gb.output(name, ["N", S], np.int64)
    gb.output("residual", ["N", S])
    gb.output("status", ["N"], np.int64)


def batched_graph(em, flags: tuple[bool, bool, bool], dtype: np.dtype, res: list, coords,
                  noise: Sequence[Sequence[float]] | None = None):  # fmt: skip
    """The batched graph: the estimator program, one node per scalar operation over ``N``.

    ``noise`` (per sensor 6 standard deviations, N and N m): the solve weighted by it, fixed in
    the graph (:func:`~torchcontact.estimation.programs.estimate_program`).

    Returns:
        ``(GraphBuilder, input shapes)``.
    """
    from torchcontact.estimation.programs import program

    moving_base, torque_rows, with_cov = flags
    gb = GraphBuilder(dtype, "torchcontact_estimator")
    S, K, nv = len(em.sensors), len(em.slots), em.tree.nv
    shapes = base_shapes(nv, S, K)
    if moving_base:
        shapes.update({k: ["N", 3] for k in fmt.BASE_INPUTS})
    if torque_rows:
        shapes.update({k: ["N", nv] for k in fmt.TORQUE_INPUTS})
    if with_cov:
        shapes[fmt.COVARIANCE_INPUT] = ["N", S, 6, 6]
    extra = list(dict.fromkeys(c for rg, _ in res for c in rg.extra))
    if res:
        shapes[fmt.EXTRA] = ["N", len(extra)]
        for rg, _ in res:
            if rg.state_shape:
                shapes[fmt.state_in(rg.sensor)] = ["N", *rg.state_shape]
    for name, sh in shapes.items():
        gb.input(name, sh)
    n = gb.op("Slice", gb.op("Shape", "q"), gb.i([0]), gb.i([1]))
    readings = gb.op("Reshape", gb.op("Sub", "ft", "ft_residual"), gb.i([-1, 6 * S]))
    states = []
    if res:
        # chained corrections: each reads q, qd, qdd (and extra columns) and corrects a sensor
        src = gb.op("Concat", "q", "qd", "qdd", fmt.EXTRA, axis=1)
        columns = fmt.JointColumns(em.model.joint_names, extra)

        def select(cols) -> str:
            return gb.op("MatMul", src, gb.f(fmt.selection(cols, columns)))

        def state(rg, to: int) -> str:
            return gb.op("Cast", fmt.state_in(rg.sensor), to=to)

        for _r, rg, c, h in chain_corrections(gb, res, select, state):
            P = np.zeros((6, 6 * S))
            s = list(em.sensor_names).index(rg.sensor)
            P[:, 6 * s : 6 * s + 6] = np.eye(6)
            readings = gb.op("Sub", readings, gb.op("MatMul", c, gb.f(P)))
            if h is not None:
                gb.op("Identity", h, out=fmt.state_out(rg.sensor))
                states.append((fmt.state_out(rg.sensor), ["N", *rg.state_shape], rg.dtype))
    prog = program(em, "estimate", *flags, **({} if noise is None else {"noise": noise}))
    ins = _program_inputs(gb, em, readings)
    for k in fmt.BASE_INPUTS:
        ins[k] = k
    ins.update({k: k for k in fmt.TORQUE_INPUTS})
    if with_cov:
        ins["ft_cov"] = gb.op("Reshape", fmt.COVARIANCE_INPUT, gb.i([-1, 36 * S]))
    cols = {k: gb.fresh(k) for k in prog.outputs}
    emit_program(gb, prog, {k: v for k, v in ins.items() if k in prog.inputs}, cols, n)
    _estimator_outputs(gb, cols, K, nv, S, coords)
    if with_cov:
        gb.op("Reshape", cols["cov"], gb.i([-1, K, 6, 6]), out="covariance")
        gb.output("covariance", ["N", K, 6, 6])
    for name, sh, dt in states:
        gb.output(name, sh, dt)
    return gb, shapes


def constrained_graph(em: EstimationModel, cones: tuple, dtype: np.dtype,
                      noise: Sequence[Sequence[float]] | None = None):  # fmt: skip
    """The friction-cone constrained estimator of a layout as one batched graph.

    The program of :func:`~torchcontact.estimation.programs.estimate_program` with ``cones``:
    the pseudo-inverse solve, then the interior-point iterations as one ``Loop``. Inputs are the
    fixed-base ones and :data:`~torchcontact.onnx.format.CONE_INPUTS`; outputs
    :data:`~torchcontact.onnx.format.ESTIMATOR_OUTPUTS` then
    :data:`~torchcontact.onnx.format.CONE_OUTPUTS` (``converged`` bool, ``iterations`` int64,
    ``cone_active`` bool).

    Args:
        em: the layout.
        cones: ``(iterations, eps, tol, stop, prior)`` (:meth:`FrictionCones.program_flags`).
        dtype: float32 or float64.
        noise: per sensor 6 standard deviations: the solve weighted by them (as
            :func:`batched_graph`).

    Returns:
        ``(GraphBuilder, input shapes)``.
    """
    from torchcontact.estimation.programs import program

    gb = GraphBuilder(dtype, "torchcontact_constrained")
    S, K, nv = len(em.sensors), len(em.slots), em.tree.nv
    shapes = {**base_shapes(nv, S, K), "normals": ["N", K, 3], "friction": ["N", K],
              "pushing": ["N", K]}  # fmt: skip
    for name, sh in shapes.items():
        gb.input(name, sh)
    n = gb.op("Slice", gb.op("Shape", "q"), gb.i([0]), gb.i([1]))
    readings = gb.op("Reshape", gb.op("Sub", "ft", "ft_residual"), gb.i([-1, 6 * S]))
    prog = program(em, "estimate", False, False, False, tuple(cones), False, False,
                   **({} if noise is None else {"noise": noise}))  # fmt: skip
    ins = _program_inputs(gb, em, readings)
    ins["normals"] = gb.op("Reshape", "normals", gb.i([-1, 3 * K]))
    ins["friction"] = "friction"
    # known slots never push (as the estimator's cone inputs)
    ins["pushing"] = gb.op("Mul", "pushing", gb.f([float(k != "known") for k in em.kinds]))
    cols = {k: gb.fresh(k) for k in prog.outputs}
    emit_program(gb, prog, {k: v for k, v in ins.items() if k in prog.inputs}, cols, n)
    _estimator_outputs(gb, cols, K, nv, S, tuple(range(nv)))
    as_bool = onnx_type(bool)
    gb.op("Cast", cols["converged"], to=as_bool, out="converged")
    gb.op("Cast", cols["iterations"], to=onnx_type(np.int64), out="iterations")
    gb.op("Cast", cols["cone_active"], to=as_bool, out="cone_active")
    gb.output("converged", ["N", S], bool)
    gb.output("iterations", ["N", S], np.int64)
    gb.output("cone_active", ["N", K], bool)
    return gb, shapes
