"""The ONNX building blocks: bilinear stages traced from scalar code, the program emitter."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch

import torchcontact as tc
from torchcontact import kernels
from torchcontact import spatial as sp
from torchcontact._scalar import mul
from torchcontact.onnx.builder import GraphBuilder, Operand, bilinear, emit_program
from torchcontact.onnx.step.forms import force_to_child as _force_to_child
from torchcontact.onnx.step.forms import force_to_parent as _force_to_parent
from torchcontact.onnx.step.forms import motion_to_child as _motion_to_child
from torchcontact.onnx.step.forms import skew as _skew


def _run(gb, feeds):
    s = ort.InferenceSession(gb.model().SerializeToString(), providers=["CPUExecutionProvider"])
    return s.run(None, feeds)


def test_bilinear_stage_matches_its_scalar_code():
    """Row-wise cross products with a per-row constant: rows differ, terms are gathered."""
    rng = np.random.default_rng(0)
    A, B = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    scale = [1.0, 2.0, -1.0, 0.5, 3.0]
    gb = GraphBuilder(np.float64)
    a = gb.input("a", [5, 4])
    b = gb.input("b", [5, 4])

    def fn(r, x, y):  # scale_r (x x y) + x: bilinear, with linear terms and a row constant
        c = sp.v_cross(tuple(x[:3]), tuple(y[:3]))
        return [*(mul(scale[r], v) for v in c), *x[:3]]

    out = bilinear(gb, Operand(a, 4, one=3), Operand(b, 4, one=3), 5, fn, 6)
    gb.op("Identity", out, out="y")
    gb.output("y", [5, 7])
    ones = np.ones((5, 1))
    (y,) = _run(gb, {"a": np.hstack([A, ones]), "b": np.hstack([B, ones])})
    want = np.hstack([np.cross(A, B) * np.array(scale)[:, None], A, ones])
    np.testing.assert_allclose(y, want, atol=1e-14)


def test_bilinear_refuses_higher_degree_and_other_ops():
    gb = GraphBuilder(np.float64)
    a = gb.input("a", [2, 3])
    with pytest.raises(ValueError, match="degree > 2"):
        bilinear(gb, Operand(a, 3), None, 2, lambda r, x, _: [mul(mul(x[0], x[1]), x[2])], 1)
    with pytest.raises(ValueError, match="cannot contain 'sqrt'"):
        bilinear(gb, Operand(a, 3), None, 2, lambda r, x, _: [tc._scalar.sqrt(x[0])], 1)


def test_adjoint_forms_equal_the_spatial_transforms():
    """The (R, [p]x R) forms the step graph traces are spatial's motion and force transforms."""
    rng = np.random.default_rng(1)
    for _ in range(5):
        R = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64))[0].numpy()
        p, v = rng.normal(size=3), rng.normal(size=6)
        T = (sp.const_mat(R), sp.const_vec(p))
        pR = sp.m_mul(_skew(T[1]), T[0])
        vv = (tuple(v[:3]), tuple(v[3:]))
        for ours, theirs in ((_motion_to_child, sp.motion_to_child),
                             (_force_to_parent, sp.force_to_parent),
                             (_force_to_child, sp.force_to_child)):  # fmt: skip
            got = np.array([*ours(T[0], pR, vv)[0], *ours(T[0], pR, vv)[1]], dtype=float)
            want = np.array([*theirs(T, vv)[0], *theirs(T, vv)[1]], dtype=float)
            np.testing.assert_allclose(got, want, atol=1e-12)


def test_emitted_program_matches_eager():
    """A program with every scalar op kind, emitted node by node, equals its eager run."""
    from torchcontact._scalar import (
        cos,
        div,
        gt,
        isfinite,
        logical_and,
        logical_not,
        logical_or,
        neg,
        select,
        sin,
        sqrt,
        sub,
    )

    def fn(x):
        a, b = x["u"]
        m = logical_and(gt(a, 0.0), logical_not(logical_or(gt(b, 2.0), logical_not(isfinite(b)))))
        r = select(m, div(sin(a), sqrt(mul(b, b))), neg(cos(b)))
        return {"y": [r, sub(a, 1.5), 2.0], "z": [select(m, 1.0, 0.0)]}

    prog = kernels.Program("t", fn, {"u": 2}, {"y": 3, "z": 1}, "test|emit")
    u = torch.tensor([[0.3, 1.2], [-0.4, 0.5], [0.7, 3.0], [1.0, float("nan")]],
                     dtype=torch.float64)  # fmt: skip
    want = kernels.run_eager(prog, {"u": u})
    gb = GraphBuilder(np.float64)
    gb.input("u", ["N", 2])
    n = gb.op("Slice", gb.op("Shape", "u"), gb.i([0]), gb.i([1]))
    emit_program(gb, prog, {"u": "u"}, {"y": "y", "z": "z"}, n)
    gb.output("y", ["N", 3])
    gb.output("z", ["N", 1])
    y, z = _run(gb, {"u": u.numpy()})
    np.testing.assert_allclose(y, want["y"].numpy(), atol=1e-15, equal_nan=True)
    np.testing.assert_array_equal(z, want["z"].numpy())


def test_fold_linear_chains():
    """Constant-matrix chains merge (right, left, Gemm bias, column scaling, a dynamic Gemm C,
    float64 constants in a float32 graph); a value an If branch reads, or used twice, stays."""
    from onnx import TensorProto

    from torchcontact.onnx.builder import fold_linear_chains

    rng = np.random.default_rng(1)
    C = [rng.normal(size=(4, 4)) for _ in range(6)]
    gb = GraphBuilder(np.float32)
    x = gb.input("x", [3, 4])
    a = gb.op("Gemm", gb.op("MatMul", x, gb.f(C[0])), gb.f(C[1]), gb.f(np.ones((1, 4))))
    a = gb.op("Mul", gb.op("Gemm", x, gb.f(C[2]), gb.f(np.ones(4)), transB=1), gb.f([[2.0] * 4]))
    s = gb.op("Add", a, gb.op("MatMul", gb.f(C[3][:3, :3]), gb.op("MatMul", gb.f(C[4][:3, :3]), x)))
    s = gb.op("Gemm", gb.op("MatMul", s, gb.f(C[5])), gb.f(C[0]), x)  # dynamic C
    wide = gb.op("Cast", s, to=TensorProto.DOUBLE)
    gb.dtype = np.dtype(np.float64)
    w = gb.op("MatMul", gb.op("MatMul", wide, gb.f(C[1])), gb.f(C[2]))
    gb.dtype = np.dtype(np.float32)
    twice = gb.op("MatMul", x, gb.f(C[3]))
    kept = gb.op("MatMul", x, gb.f(C[4]))  # read inside the branch
    branch = gb.branch(lambda: [gb.op("MatMul", kept, gb.f(C[5]))])
    cond = gb.const(np.array([True]), bool)
    b = gb.op("If", cond, then_branch=branch, else_branch=branch)
    y = gb.op("Add", gb.op("Add", gb.op("MatMul", twice, gb.f(C[0])), twice), b)
    gb.op("Add", y, gb.op("MatMul", kept, gb.f(C[1])), out="y")  # kept: used once here too
    gb.op("Identity", w, out="w")
    gb.output("y", [3, 4])
    gb.output("w", [3, 4], np.float64)
    xv = rng.normal(size=(3, 4)).astype(np.float32)
    want = _run(gb, {"x": xv})
    n = len(gb.nodes)
    assert fold_linear_chains(gb) == 5
    assert len(gb.nodes) == n - 5
    # (the session would refuse a float32 constant in the float64 chain)
    for got, ref in zip(_run(gb, {"x": xv}), want, strict=True):
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4 * float(np.abs(ref).max()))
