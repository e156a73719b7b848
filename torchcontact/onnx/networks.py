"""Correction graphs through the builder: the physics layers as a program, the networks as nodes.

No graph torchcontact writes is traced by ``torch.onnx``:

* :func:`correction_program`: the physics layers of a :class:`~torchcontact.residual.CorrectionSpec`
  (offset, inertial layer ``Y delta``, nominal wrench) on scalars, from the estimator's own
  stages (:func:`torchcontact.estimation.stages.forward`,
  :func:`torchcontact.dynamics.backward_pass`);
  :func:`~torchcontact.onnx.builder.emit_program` writes it over ``N`` frames;
* :func:`emit_learned`: a :class:`~torchcontact.residual.ResidualMLP` or
  :class:`~torchcontact.residual.ResidualGRU` with its normalisation, from its weights (ONNX
  ``Gemm``, ``Sigmoid``, ``GRU``);
* :func:`emit_module`: a small ``nn.Module`` of ``Linear``, ``GRUCell`` and elementwise
  activations, from its ``torch.fx`` graph (:func:`torchcontact.onnx.export.export_residual`).
"""

from __future__ import annotations

import operator
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from torchcontact import kernels
from torchcontact import spatial as sp
from torchcontact._scalar import add, mul
from torchcontact.onnx.builder import GraphBuilder

__all__ = ["correction_program", "emit_learned", "emit_module", "feature_matrix"]


def correction_program(model, spec) -> kernels.Program:
    """The physics layers of a correction stack as a program.

    Inputs ``q, qd, qdd`` (nv each); outputs ``physics`` (6: the offset plus the inertial layer's
    ``Y delta``) and ``nominal`` (6: the contact-free reading the rigid-body model predicts, a
    feature of the learned layer), in the sensor's frame and measure direction.

    Args:
        model: the robot (its gravity on a fixed base).
        spec: the :class:`~torchcontact.residual.CorrectionSpec`.
    """
    from torchcontact.dynamics import backward_pass
    from torchcontact.estimation import stages
    from torchcontact.estimation.layout import EstimationModel

    em = EstimationModel.build(model, [spec.sensor], [], [])
    tree, reg = em.tree, em.regions[0]
    sub = set(model.subtree(reg.child))
    delta = {}
    for name, (m, hx, hy, hz, ixx, ixy, iyy, ixz, iyz, izz) in spec.inertial:
        i = model.body_names.index(name)
        Q = np.asarray(tree.bodies[i].Q, float)  # R_link_internal
        Io = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        delta[i] = (
            float(m),
            sp.const_vec(Q.T @ np.array([hx, hy, hz])),
            sp.const_mat(Q.T @ Io @ Q),
        )
    offset = [0.0] * 6 if spec.offset is None else [float(v) for v in spec.offset]
    zero = (sp.ZERO3, sp.ZERO3)
    nv = model.nv

    def in_sensor(X, f) -> list:
        """The subtree's wrenches ``f`` summed at the sensor: its frame, its sign."""
        F, _ = backward_pass(tree, X, [f[i] if i in sub else zero for i in range(len(f))])
        Fs = sp.force_to_child(reg.T_child_sensor, F[reg.child])
        return [mul(reg.sign, v) for v in (*Fs[0], *Fs[1])]

    def fn(x: dict[str, list]) -> dict[str, list]:
        X, v, a, f = stages.forward(em, x["q"], x["qd"], x["qdd"], None)
        physics = list(offset)
        if delta:  # the parameter change as the bodies' inertias: Y delta
            fd = [zero] * len(f)
            for i, (m, h, Io) in delta.items():
                fd[i] = sp.body_wrench_params(m, h, Io, v[i], a[i])
            physics = [add(p, y) for p, y in zip(physics, in_sensor(X, fd), strict=True)]
        nominal = in_sensor(X, f) if spec.nominal else [0.0] * 6
        return {"physics": physics, "nominal": nominal}

    key = f"corr|{em.key}|{hash((spec.offset, spec.inertial, spec.nominal))}"
    return kernels.Program("correction", fn, {"q": nv, "qd": nv, "qdd": nv},
                           {"physics": 6, "nominal": 6}, key)  # fmt: skip


def feature_matrix(model, features, extra: Sequence[str]) -> np.ndarray:
    """``(3 nv + E + 2 nv + 6, F)``: features from ``[q, qd, qdd, extra, sin q, cos q, nominal]``.

    One 0/1 selection per feature name of :meth:`FeatureSpec.names` (``sin.j``, ``cos.j``,
    ``q.j``, ``qd.j``, ``qdd.j``, ``nominal.<axis>``, an extra column).
    """
    nv = model.nv
    j = {name: i for i, name in enumerate(model.joint_names)}
    e = {name: i for i, name in enumerate(extra)}
    base = {"q": 0, "qd": nv, "qdd": 2 * nv, "sin": 3 * nv + len(e), "cos": 4 * nv + len(e)}
    axes = ("fx", "fy", "fz", "mx", "my", "mz")
    names = features.names(model)
    sel = np.zeros((5 * nv + len(e) + 6, len(names)))
    for col, name in enumerate(names):
        kind, _, rest = name.partition(".")
        if kind in base and rest in j:
            sel[base[kind] + j[rest], col] = 1.0
        elif kind == "nominal" and rest in axes:
            sel[5 * nv + len(e) + axes.index(rest), col] = 1.0
        else:
            sel[3 * nv + e[name], col] = 1.0
    return sel


def _linear(gb: GraphBuilder, x: str, layer: nn.Linear) -> str:
    w = layer.weight.detach().double().numpy()
    if layer.bias is None:
        return gb.op("MatMul", x, gb.f(w.T))
    return gb.op("Gemm", x, gb.f(w), gb.f(layer.bias.detach().double().numpy()), transB=1)


def _gru(gb: GraphBuilder, x: str, h: str, w_ih, w_hh, b_ih, b_hh) -> tuple[str, str]:
    """One GRU step (torch's gate equations, ONNX ``GRU`` with ``linear_before_reset``).

    Args:
        gb: the graph.
        x: ``(N, in)`` input.
        h: ``(N, H)`` state.
        w_ih: torch's ``(3H, in)`` input weights (gates r, z, n).
        w_hh: ``(3H, H)`` state weights.
        b_ih: ``(3H,)`` input biases.
        b_hh: ``(3H,)`` state biases.

    Returns:
        ``(output, next state)``, both ``(N, H)``.
    """
    H = w_hh.shape[1]

    def zrn(w: torch.Tensor) -> np.ndarray:  # torch's (r, z, n) rows as ONNX's (z, r, h)
        w = w.detach().double().numpy()
        return np.concatenate([w[H : 2 * H], w[0:H], w[2 * H :]])[None]

    B = np.concatenate([zrn(b_ih), zrn(b_hh)], axis=-1)
    X = gb.op("Unsqueeze", x, gb.i([0]))  # (seq 1, N, in)
    h0 = gb.op("Unsqueeze", h, gb.i([0]))  # (1, N, H)
    _, yh = gb.op("GRU", X, gb.f(zrn(w_ih)), gb.f(zrn(w_hh)), gb.f(B), "", h0, n_out=2,
                  hidden_size=H, linear_before_reset=1)  # fmt: skip
    out = gb.op("Squeeze", yh, gb.i([0]))
    return out, out


def emit_learned(gb: GraphBuilder, net, x: str, h: str | None = None) -> tuple[str, str | None]:
    """A learned layer with its normalisation: features -> residual (and next state).

    Args:
        gb: the graph.
        net: a :class:`~torchcontact.residual.ResidualMLP` or ``ResidualGRU``.
        x: ``(N, F)`` features.
        h: ``(N, L, H)`` state of a GRU.

    Returns:
        ``(residual (N, 6), next state (N, L, H) or None)``.
    """
    mean, std = (gb.f(getattr(net, k).detach().double().numpy())
                 for k in ("feature_mean", "feature_std"))  # fmt: skip
    z = gb.op("Div", gb.op("Sub", x, mean), std)
    h_out = None
    if net.kind == "mlp":
        y = z
        for layer in net.net:
            y = _linear(gb, y, layer) if isinstance(layer, nn.Linear) else _activation(gb, y, layer)
    else:
        L = net.layers
        states, inp = [], z
        for k in range(L):
            hk = gb.op("Reshape", gb.op("Gather", h, gb.i(k), axis=1), gb.i([-1, net.hidden]))
            names = ("weight_ih", "weight_hh", "bias_ih", "bias_hh")
            inp, hn = _gru(gb, inp, hk, *(getattr(net.gru, f"{w}_l{k}") for w in names))
            states.append(gb.op("Unsqueeze", hn, gb.i([1])))
        h_out = states[0] if L == 1 else gb.op("Concat", *states, axis=1)
        y = _linear(gb, gb.op("Concat", inp, z, axis=1), net.head)
    tstd, tmean = (gb.f(getattr(net, k).detach().double().numpy())
                   for k in ("target_std", "target_mean"))  # fmt: skip
    return gb.op("Add", gb.op("Mul", y, tstd), tmean), h_out


_ACTIVATIONS = {nn.Tanh: "Tanh", nn.Sigmoid: "Sigmoid", nn.ReLU: "Relu"}


def _activation(gb: GraphBuilder, x: str, mod: nn.Module) -> str:
    if isinstance(mod, nn.SiLU):
        return gb.op("Mul", x, gb.op("Sigmoid", x))
    for cls, op in _ACTIVATIONS.items():
        if isinstance(mod, cls):
            return gb.op(op, x)
    raise ValueError(f"no ONNX emission for layer {type(mod).__name__}")


_FUNCTIONS = {operator.add: "Add", operator.sub: "Sub", operator.mul: "Mul",
              operator.truediv: "Div", torch.add: "Add", torch.mul: "Mul", torch.tanh: "Tanh",
              torch.sigmoid: "Sigmoid", torch.relu: "Relu"}  # fmt: skip


def emit_module(gb: GraphBuilder, module: nn.Module, inputs: Sequence[str]) -> list[str]:
    """A module's ``forward`` from its ``torch.fx`` graph, one ONNX node per operation.

    Handles ``nn.Linear``, ``nn.GRUCell``, ``nn.Tanh``/``Sigmoid``/``ReLU``/``SiLU`` modules,
    elementwise ``+ - * /``, ``torch.cat`` and tuple outputs: the small networks of F/T
    residual models.

    Raises:
        ValueError: an operation outside that set (the message names it), or a module that
            ``torch.fx`` cannot trace.
    """
    import torch.fx

    try:
        graph = torch.fx.symbolic_trace(module).graph
    except Exception as e:  # noqa: BLE001 - fx raises many kinds on untraceable code
        raise ValueError(f"{type(module).__name__} cannot be traced by torch.fx: {e}") from None
    mods = dict(module.named_modules())
    vals: dict[str, object] = {}
    args = iter(inputs)

    def v(a):
        if isinstance(a, torch.fx.Node):
            return vals[a.name]
        if isinstance(a, (int, float)):
            return gb.f(float(a))
        raise ValueError(f"no ONNX emission for the constant {a!r}")

    for node in graph.nodes:
        if node.op == "placeholder":
            vals[node.name] = next(args)
        elif node.op == "call_module":
            m = mods[node.target]
            if isinstance(m, nn.Linear):
                vals[node.name] = _linear(gb, v(node.args[0]), m)
            elif isinstance(m, nn.GRUCell):
                vals[node.name] = _gru(gb, v(node.args[0]), v(node.args[1]), m.weight_ih,
                                       m.weight_hh, m.bias_ih, m.bias_hh)[1]  # fmt: skip
            else:
                vals[node.name] = _activation(gb, v(node.args[0]), m)
        elif node.op == "call_function" and node.target in _FUNCTIONS:
            vals[node.name] = gb.op(_FUNCTIONS[node.target], *(v(a) for a in node.args))
        elif node.op == "call_function" and node.target is torch.cat:
            dim = node.kwargs.get("dim", node.args[1] if len(node.args) > 1 else 0)
            vals[node.name] = gb.op("Concat", *(v(a) for a in node.args[0]), axis=int(dim))
        elif node.op == "output":
            res = node.args[0]
            return [v(a) for a in res] if isinstance(res, (tuple, list)) else [v(res)]
        else:
            raise ValueError(f"no ONNX emission for {node.op} {node.target}")
    raise ValueError("the traced module has no output")
