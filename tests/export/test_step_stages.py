"""The single-frame graph stage by stage against :mod:`torchcontact.estimation.stages`.

Each stage of :mod:`torchcontact.onnx.step` is probed (its values made graph outputs, the graph
run by onnxruntime in float64) and compared with the estimator's stage functions evaluated on
Python floats for the same frame of the same (pruned) layout: poses, twists, accelerations and
body wrenches (``forward``), ``b`` (``region_rhs``), Gram matrices (``contact_maps``), the solve
(:func:`torchcontact.solve.solve_program`), contact wrenches and joint torques
(``contact_wrenches``, ``backward``), and the inputs' status bits (the estimator program's). On
random frames of the tcarm (one and two sensors, moving base, every slot kind) and the iCub arm
(pruned tree). Tolerance: 1e-12 relative to ``max(1, |reference|)`` for the stages before the
solve; the solve and what follows it (Gauss-Jordan against pivoted Cholesky, the same pivots)
to 1e-12 relative to the largest entry of ``G`` times its conditioning on the accepted pivots.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
from export_scenes import LAYOUTS, robot_model, scene
from onnx import TensorProto, helper

import torchcontact as tc
from torchcontact import spatial as sp
from torchcontact.estimation import programs, stages
from torchcontact.kernels import run_eager
from torchcontact.onnx import step
from torchcontact.onnx.step.context import Flags
from torchcontact.solve import solve_program

TOL = 1e-12
FRAMES = 6


class Probe:
    """A step graph of one layout whose stage values are outputs."""

    def __init__(self, name: str) -> None:
        lay = LAYOUTS[name]
        self.name = name
        est = tc.ContactEstimator(robot_model(lay["robot"]), lay["sensors"])
        full = est.layout(lay["links"], lay["kinds"])
        coords = full.torque_joints(lay["joints"])
        self.flags = Flags(*lay["flags"])
        self.full = full
        self.ctx = step.context(full, self.flags, np.float64, (), coords)
        gb = self.ctx.gb
        x = gb.input("x", [1, self.ctx.lay.size])
        self.values = step.stages(self.ctx, x)
        self.names = []
        for key in ("status", "T", "VA", "f0", "Fb", "b", "G", "y", "rank", "fm", "tau"):
            vals = self.values[key]
            for r, val in enumerate(vals if isinstance(vals, list) else [vals]):
                if val is None:
                    continue
                out = f"probe.{key}.{r}"
                gb.op("Identity", val, out=out)
                gb.outputs.append(helper.make_tensor_value_info(out, TensorProto.DOUBLE, None))
                self.names.append(out)
        self.session = ort.InferenceSession(
            gb.model().SerializeToString(), providers=["CPUExecutionProvider"]
        )

    def run(self, frame: dict) -> dict:
        """The probed values of one frame (``scene`` arrays of one frame)."""
        lay = self.ctx.lay
        x = np.zeros((1, lay.size))
        for name in lay.fields:
            start, stop, _ = lay.span(name)
            x[0, start:stop] = np.asarray(frame[name], float).reshape(-1)
        outs = self.session.run(self.names, {"x": x})
        got: dict = {}
        for name, value in zip(self.names, outs, strict=True):
            _, key, r = name.split(".")
            got.setdefault(key, {})[int(r)] = value
        return got


@pytest.fixture(scope="module", params=["tcarm", "tcarm2", "panda", "icub"])
def probe(request):
    return Probe(request.param)


def _frames(name: str) -> list[dict]:
    x = scene(name, FRAMES, seed=11)
    return [{k: v[i] for k, v in x.items()} for i in range(FRAMES)]


def _close(got, want, what: str, scale: float | None = None) -> None:
    got, want = np.asarray(got, float), np.asarray(want, float).reshape(np.shape(got))
    s = max(1.0, float(np.max(np.abs(want)))) if scale is None else scale
    err = float(np.max(np.abs(got - want))) if want.size else 0.0
    assert err <= TOL * s, f"{what}: error {err:.3g} > {TOL * s:.3g}"


def _reference(probe: Probe, f: dict) -> dict:
    """The estimator's stages on Python floats for one clean frame."""
    em = probe.ctx.em
    fl = lambda a: [float(v) for v in np.asarray(a).reshape(-1)]  # noqa: E731
    q, qd, qdd = fl(f["q"]), fl(f["qd"]), fl(f["qdd"])
    base = None
    if probe.flags.moving_base:
        base = {k: fl(f[k]) for k in ("omega", "domega", "proper_acc")}
    readings = [fl(f["ft"][s] - f["ft_residual"][s]) for s in range(len(em.regions))]
    act = [1.0 if a > 0.5 else 0.0 for a in f["active"]]
    pos = [fl(p) for p in f["positions"]]
    dirs = [fl(d) for d in f["directions"]]
    wr = [fl(w) for w in f["wrenches"]]
    tau_meas = tau_mask = None
    if probe.flags.torque_rows:
        tau_meas = fl(f["tau_measured"])
        tau_mask = [1.0 if m > 0.5 else 0.0 for m in f["tau_mask"]]
    X, v, a, fb = stages.forward(em, q, qd, qdd, base)
    known: dict = {}
    for k, slot in enumerate(em.slots):
        if slot.kind == "known":
            w = (tuple(act[k] * c for c in wr[k][:3]), tuple(act[k] * c for c in wr[k][3:]))
            known.setdefault(slot.body, []).append(
                stages.wrench_on_body(slot, stages.contact_point(slot, pos[k]), w)
            )
    _, tau_b, b = stages.region_rhs(em, X, fb, readings, known, tau_meas, tau_mask)
    maps, grams = stages.contact_maps(em, X, pos, dirs, act, tau_mask)
    ys, ranks, res = [], [], []
    for r, reg in enumerate(em.regions):
        if all(em.slots[k].kind == "known" for k in reg.slots):
            ys.append([0.0] * len(b[r]))
            ranks.append(0.0)
            res.append(float(np.linalg.norm(b[r])))
            continue
        y, rank, rr, _ = solve_program(grams[r], b[r], em.rank_rtol)
        ys.append(y)
        ranks.append(rank)
        res.append(rr)
    w = stages.contact_wrenches(em, maps, ys, wr, act)
    tau = stages.backward(em, X, tau_b, pos, w)
    T = [None] * len(em.tree.bodies)
    T[0] = (sp.EYE3, sp.ZERO3)
    for i in range(1, len(T)):
        T[i] = sp.pose_compose(T[em.tree.bodies[i].parent], X[i])
    return dict(T=T, v=v, a=a, f=fb, b=b, G=grams, y=ys, rank=ranks, res=res, w=w, tau=tau)


def test_forward_stage(probe):
    """Poses, twists, accelerations and body wrenches of every body (``stages.forward``)."""
    for f in _frames(probe.name):
        got, ref = probe.run(f), _reference(probe, f)
        T = got["T"][0].reshape(-1, 4, 4)  # homogeneous, row-major
        for i, (R, p) in enumerate(ref["T"]):
            H = np.eye(4)
            H[:3, :3], H[:3, 3] = np.array(R, float), p
            _close(T[i], H, f"T[{i}]")
            Ti = (sp.const_mat(T[i, :3, :3]), sp.const_vec(T[i, :3, 3]))
            va = got["VA"][0][i]
            for name, cols in (("v", slice(0, 6)), ("a", slice(6, 12))):
                mo = sp.motion_to_child(Ti, (tuple(va[cols][:3]), tuple(va[cols][3:])))
                _close([*mo[0], *mo[1]], [*ref[name][i][0], *ref[name][i][1]], f"{name}[{i}]")
            f0 = got["f0"][0][i]
            fo = sp.force_to_child(Ti, (tuple(f0[:3]), tuple(f0[3:])))
            _close([*fo[0], *fo[1]], [*ref["f"][i][0], *ref["f"][i][1]], f"f[{i}]")


def test_region_stage(probe):
    """Each region's ``b`` (``region_rhs``) and Gram matrix (``contact_maps``)."""
    for f in _frames(probe.name):
        got, ref = probe.run(f), _reference(probe, f)
        for r in range(len(ref["b"])):
            _close(got["b"][r].reshape(-1), ref["b"][r], f"b[{r}]")
            _close(got["G"][r], np.array(ref["G"][r], float), f"G[{r}]")


def test_solve_stage(probe):
    """The minimum-norm solve (:func:`torchcontact.solve.solve_program`): rank, ``G y``."""
    for f in _frames(probe.name):
        got, ref = probe.run(f), _reference(probe, f)
        for r, y_ref in enumerate(ref["y"]):
            if r not in got["y"]:
                continue
            G = np.array(ref["G"][r], float)
            assert int(got["rank"][r].item()) == int(ref["rank"][r]), f"rank[{r}]"
            y = got["y"][r][:, 0]
            # G y = P_range(G) b is unique (y is not, on a singular G)
            scale = max(1.0, float(np.abs(G).max())) * max(1.0, float(np.abs(y_ref).max()))
            _close(G @ y, G @ np.array(y_ref, float), f"G y[{r}]", scale * _cond(G, y_ref))


def _cond(G: np.ndarray, y: list) -> float:
    """Conditioning of ``G`` on its range (what the solve's rounding is relative to)."""
    ev = np.linalg.eigvalsh(G)
    big = ev.max()
    kept = ev[ev > 1e-10 * max(big, 1e-300)]
    return float(big / kept.min()) if kept.size else 1.0


def test_output_stage(probe):
    """Contact wrenches (``contact_wrenches``) and joint torques (``backward``)."""
    coords = probe.ctx.coords
    for f in _frames(probe.name):
        got, ref = probe.run(f), _reference(probe, f)
        conds = [_cond(np.array(G, float), y) for G, y in zip(ref["G"], ref["y"], strict=True)]
        scale = max(1.0, float(np.max(np.abs([[*w[0], *w[1]] for w in ref["w"]] or [[0.0]]))))
        scale *= max(conds)
        fm = got["fm"][0][: len(ref["w"])]
        for k, w in enumerate(ref["w"]):
            _close(fm[k, :6], [*w[0], *w[1]], f"w[{k}]", scale)
        tau = got["tau"][0][0]
        _close(tau[list(coords)], np.array(ref["tau"], float)[list(coords)], "tau", 100 * scale)


def test_input_stage_status_bits(probe):
    """The inputs' status bits equal the estimator program's on faulty frames."""
    em = probe.ctx.em
    prog = programs.estimate_program(em, *probe.flags.as_tuple())
    frames = _frames(probe.name)
    faults = [("ft", (0, 1), np.nan), ("q", (2,), np.inf), ("positions", (0, 1), np.nan),
              ("ft_residual", (0, 4), -np.inf)]  # fmt: skip
    bad = []
    for (key, idx, value), f in zip(faults, frames, strict=False):
        f = {k: np.array(v, float) for k, v in f.items()}
        f[key][idx] = value
        bad.append(f)
    got = [int(probe.run(f)["status"][0].item()) for f in bad]
    batch = {k: np.stack([f[k] for f in bad]) for k in bad[0]}
    want = run_eager(prog, _program_inputs(probe, batch))["status"][:, 0].tolist()
    assert {int(w) & int(tc.Status.IMPLAUSIBLE) for w in want} == {0}  # no limits set here
    assert got == [int(w) & ~int(tc.Status.OUTPUT_NONFINITE) for w in want]
    assert all(got)


def _program_inputs(probe: Probe, f: dict) -> dict:
    import torch

    em = probe.ctx.em
    n = len(f["q"])
    t = lambda a: torch.as_tensor(np.asarray(a, float).reshape(n, -1))  # noqa: E731
    names = ["q", "qd", "qdd", "active", "positions"]
    names += ["directions"] * ("force_dir" in em.kinds) + ["wrenches"] * ("known" in em.kinds)
    names += ["omega", "domega", "proper_acc"] * probe.flags.moving_base
    names += ["tau_measured", "tau_mask"] * probe.flags.torque_rows
    ins = {k: t(f[k]) for k in names}  # the program's inputs have the graph's names
    ins["ft"] = t(f["ft"] - f["ft_residual"])
    if probe.flags.covariance:
        ins["ft_cov"] = t(f["ft_cov"])
    return ins


def test_solve_full_rank_sweep_and_pivoted_branches():
    """The solve's two roads (``onnx.step.solve``) against ``solve_program``, and which one ran.

    On one region's ``G``, ``b`` as graph inputs (float64): full-rank ``G`` (badly scaled as a
    whitened system is, and well scaled) must take the sweep (its ``full`` output true) and
    equal ``G^-1 b``; rank-deficient, zero and nearly singular ``G`` (below the rank rule) must
    fail the sweep's test and give the pivoted elimination's rank and ``G y``.
    """
    from torchcontact.onnx.step import solve

    lay = LAYOUTS["icub"]
    full_em = tc.ContactEstimator(robot_model(lay["robot"]), lay["sensors"]).layout(
        lay["links"], lay["kinds"]
    )
    ctx = step.context(full_em, Flags(), np.float64)
    gb, R = ctx.gb, 6
    G, b = gb.input("G", [R, R]), gb.input("b", [R, 1])
    # full_rank_possible's count: above 2.5 when the frame may have full rank
    possible = gb.input("possible", [1, 1])
    y, rank = solve.solve_region(ctx, G, b, R, 3, 1, None, possible)
    d0 = gb.op("GatherElements", G, gb.i(np.arange(R)[:, None]), axis=1)
    dmax = gb.op("ReduceMax", d0, keepdims=1)  # unweighted graphs: rtol folded into the test
    ok, _ = solve._sweep(ctx, G, b, R, d0, dmax, jacobi=False)
    full = gb.op("ReduceMin", gb.cast(ok), keepdims=0)
    for out in (y, rank, full):
        gb.output(out, None)
    sess = ort.InferenceSession(gb.model().SerializeToString(), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(3)
    A = rng.normal(size=(R, 15))
    scaled = np.diag([1e2, 1e2, 1e2, 1e-1, 1e-1, 1e-1])
    A5 = A.copy()
    A5[:, 5:] = 0.0
    A5[5] = A5[0] + A5[1]  # rank 5
    tiny = A.copy()
    tiny[5] = tiny[0] + 1e-9 * tiny[5]  # rank 6, below the rank rule
    cases = [(A @ A.T, True), (scaled @ A @ A.T @ scaled, True), (A5 @ A5.T, False),
             (np.zeros((R, R)), False), (tiny @ tiny.T, False)]  # fmt: skip
    for i, (Gv, fast) in enumerate(cases):
        bv = rng.normal(size=(R, 1))
        for poss in (3.0, 2.0):
            yv, rv, fv = sess.run(None, {"G": Gv, "b": bv, "possible": np.array([[poss]])})
            assert bool(fv) == fast, f"case {i}: sweep test {bool(fv)}"
            y_ref, r_ref, _, _ = solve_program(Gv.tolist(), bv[:, 0].tolist(), ctx.em.rank_rtol)
            assert int(rv.item()) == int(r_ref), f"case {i}: rank {rv.item()} vs {r_ref}"
            scale = max(1.0, float(np.abs(Gv).max())) * max(1.0, float(np.abs(y_ref).max()))
            _close(Gv @ yv[:, 0], Gv @ np.array(y_ref), f"case {i}: G y", scale * _cond(Gv, y_ref))


def test_learned_layer_folding():
    """``fold_affine_ends``: the feature map, normalisation and output scaling folded into the
    MLP's first and last ``Gemm`` (4 nodes fewer in the network, and the feature map's ``MatMul``
    before it), the same output; a GRU keeps its first layer (its head is folded)."""
    import torch

    from torchcontact.onnx.builder import GraphBuilder
    from torchcontact.onnx.networks import emit_learned
    from torchcontact.onnx.step.corrections import fold_affine_ends
    from torchcontact.residual import ResidualGRU, ResidualMLP

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    V, F = 9, 7
    pre = np.zeros((V, F))
    pre[rng.permutation(V)[:F], np.arange(F)] = 1.0
    v = rng.normal(size=(3, V)).astype(np.float32)
    for net in (ResidualMLP(F, 16, 2), ResidualGRU(F, 8, layers=1)):
        net.set_normalisation(torch.randn(64, F), torch.randn(64, 6))
        gb = GraphBuilder(np.float32, "learned")
        x = gb.input("features", ["N", F])
        h = gb.input("h_in", ["N", 1, 8]) if net.kind == "gru" else None
        y, h_out = emit_learned(gb, net, x, h)
        gb.op("Identity", y, out="residual")
        gb.output("residual", ["N", 6])
        model = gb.model()
        shift = rng.normal(size=6)
        new, folded, shifted = fold_affine_ends(model, pre, shift)
        assert folded == (net.kind == "mlp") and shifted
        feeds = {"h_in": np.zeros((3, 1, 8), np.float32)} if h else {}

        def run(m, feats, feeds=feeds):
            s = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
            names = {i.name for i in s.get_inputs()}
            return s.run(["residual"], {"features": feats, **{k: f for k, f in feeds.items()
                                                              if k in names}})[0]  # fmt: skip

        want = run(model, (v @ pre).astype(np.float32)) + shift.astype(np.float32)
        got = run(new, v if folded else (v @ pre).astype(np.float32))
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))
        removed = len(model.graph.node) - len(new.graph.node)
        assert removed == (4 if net.kind == "mlp" else 2), removed
