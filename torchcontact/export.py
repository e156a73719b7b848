"""Export the contact estimator and learned residual models to ONNX (extra ``export``).

:func:`export_estimator` writes the *whole* estimator of one robot, sensor set and contact-slot
layout as a single ONNX graph, traced from the same torch code as
:meth:`ContactEstimator.estimate <torchcontact.ContactEstimator.estimate>` (RNEA forward pass,
``b`` assembly, the residual correction of the readings, the minimum-norm solve by pivoted
Cholesky of :mod:`torchcontact.solve`, and the backward pass). The graph runs with onnxruntime
alone through :mod:`torchcontact.runtime`.

:func:`export_residual` writes any ``nn.Module`` mapping features ``(N, F)`` to an F/T residual
``(N, 6)`` (optionally with a recurrent state ``h_in -> h_out``); :func:`check_parity` compares
the file with the module.

Graph inputs of the estimator (``N`` dynamic, ``S`` sensors, ``K`` slots, ``nv`` joints)::

    q, qd, qdd   (N, nv)   joint positions (rad, m), velocities, accelerations
    ft           (N, S, 6) readings [force N; moment N m], sensor frame and measure direction
    positions    (N, K, 3) contact points in the slot's link frame, m
    directions   (N, K, 3) force directions for force_dir slots (link frame; zeros elsewhere)
    wrenches     (N, K, 6) given wrenches of known slots (link frame, about the point)
    active       (N, K)    1 where the slot is in contact, 0 elsewhere (float, model dtype)
    ft_residual  (N, S, 6) subtracted from ft before estimation (zeros: no correction)

Outputs: ``force (N, K, 3)``, ``moment (N, K, 3)``, ``joint_torques (N, nv)``, ``rank (N, S)``
int64, ``unknowns (N, S)`` int64, ``residual (N, S)``, ``status (N,)`` int64 (bits of
:data:`torchcontact.STATUS`; outputs of such frames are NaN).
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from torchcontact.contacts import KINDS, Contacts
from torchcontact.estimation import ContactEstimator
from torchcontact.model import RobotModel

__all__ = [
    "ESTIMATOR_INPUTS",
    "ESTIMATOR_OUTPUTS",
    "EstimatorGraph",
    "check_parity",
    "export_estimator",
    "export_residual",
    "export_residual_checkpoint",
]

#: Input names of an exported estimator, in order.
ESTIMATOR_INPUTS = (
    "q",
    "qd",
    "qdd",
    "ft",
    "positions",
    "directions",
    "wrenches",
    "active",
    "ft_residual",
)
#: Output names of an exported estimator, in order.
ESTIMATOR_OUTPUTS = (
    "force",
    "moment",
    "joint_torques",
    "rank",
    "unknowns",
    "residual",
    "status",
)
#: Format version of the metadata written by :func:`export_estimator`.
FORMAT = "torchcontact.estimator/1"
DEFAULT_OPSET = 18
DYNAMO = False


class EstimatorGraph(nn.Module):
    """The estimator of fixed slots as a tensor-in, tensor-out module (what gets exported).

    Holds no parameters; the robot model's tensors become constants of the traced graph.

    Args:
        estimator: a :class:`ContactEstimator` (its model's gravity and rank tolerance are baked
            into the graph).
        links: K link (or frame) names of the contact slots.
        kinds: K slot kinds (see :data:`torchcontact.KINDS`).
    """

    def __init__(
        self, estimator: ContactEstimator, links: Sequence[str], kinds: Sequence[str]
    ) -> None:
        super().__init__()
        self.est = estimator
        self.links, self.kinds = tuple(links), tuple(kinds)
        # validate the layout now (unknown links, slots outside every sensor's subtree)
        estimator.layout(self.links, self.kinds)

    def forward(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        ft: Tensor,
        positions: Tensor,
        directions: Tensor,
        wrenches: Tensor,
        active: Tensor,
        ft_residual: Tensor,
    ) -> tuple[Tensor, ...]:
        """Estimate ``N`` frames; shapes as in the module docstring."""
        est = self.est
        readings = ft - ft_residual  # residual correction (a learned model's output, or zeros)
        out = est.estimate(
            q,
            qd,
            qdd,
            {s: readings[:, i] for i, s in enumerate(est.sensor_names)},
            Contacts(self.links, self.kinds, positions, directions, wrenches, active),
            backend="eager",
        )
        names = est.sensor_names
        return (
            out.force,
            out.moment,
            out.joint_torques,
            torch.stack([out.rank[s] for s in names], -1),
            torch.stack([out.unknowns[s] for s in names], -1),
            torch.stack([out.residual[s] for s in names], -1),
            out.status,
        )


def _example_inputs(model: RobotModel, S: int, K: int, n: int = 2) -> tuple[Tensor, ...]:
    """Finite example inputs (distinct frames) for tracing."""
    g = torch.Generator().manual_seed(0)
    dt = model.dtype

    def r(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64).to(dt)

    nv = model.nv
    return (
        r(n, nv),
        r(n, nv),
        r(n, nv),
        r(n, S, 6),
        r(n, K, 3),
        r(n, K, 3) + 0.5,
        r(n, K, 6),
        torch.ones(n, K, dtype=dt),
        torch.zeros(n, S, 6, dtype=dt),
    )


def estimator_metadata(
    model: RobotModel,
    estimator: ContactEstimator,
    links: Sequence[str],
    kinds: Sequence[str],
    opset: int,
    rank_rtol: float | None,
) -> dict[str, str]:
    """The ``metadata_props`` of an exported estimator (all values are strings, JSON inside)."""
    import torchcontact

    S, K = len(estimator.sensor_names), len(links)
    shapes = {
        "q": ["N", model.nv],
        "qd": ["N", model.nv],
        "qdd": ["N", model.nv],
        "ft": ["N", S, 6],
        "positions": ["N", K, 3],
        "directions": ["N", K, 3],
        "wrenches": ["N", K, 6],
        "active": ["N", K],
        "ft_residual": ["N", S, 6],
    }
    sensors = [
        {"name": s.name, "joint": s.joint, "frame": s.frame, "direction": s.measure_direction}
        for s in estimator.sensors
    ]
    return {
        "format": FORMAT,
        "robot": model.name,
        "urdf_sha256": model.urdf_sha256,
        "joint_names": json.dumps(list(model.joint_names)),
        "sensors": json.dumps(sensors),
        "slot_links": json.dumps(list(links)),
        "slot_kinds": json.dumps(list(kinds)),
        "inputs": json.dumps(list(ESTIMATOR_INPUTS)),
        "input_shapes": json.dumps(shapes),
        "outputs": json.dumps(list(ESTIMATOR_OUTPUTS)),
        "units": json.dumps(
            {
                "q": "rad or m",
                "qd": "rad/s or m/s",
                "qdd": "rad/s^2 or m/s^2",
                "ft": "[N, N, N, N m, N m, N m]",
                "positions": "m",
                "force": "N",
                "moment": "N m",
                "joint_torques": "N m or N",
                "gravity": "m/s^2",
            }
        ),
        "frames": "positions, directions, wrenches, force, moment: the slot's link frame; "
        "moments about the contact point; ft: each sensor's declared frame and direction",
        "gravity": json.dumps([float(g) for g in model.gravity]),
        "dtype": str(model.dtype).removeprefix("torch."),
        "solver": "pivoted cholesky",
        "rank_rtol": "default" if rank_rtol is None else repr(float(rank_rtol)),
        "torchcontact_version": torchcontact.__version__,
        "torch_version": torch.__version__,
        "opset": str(opset),
    }


def _export(module, args, path, input_names, output_names, dynamic_axes, opset) -> None:
    """``torch.onnx.export`` with the TorchScript-based exporter (``dynamo=False``).

    The estimator is straight-line elementwise code, which the tracing exporter handles without
    extra dependencies; constant folding removes the model-constant arithmetic. Inputs a layout
    does not read (directions without ``force_dir`` slots, wrenches without ``known`` slots) are
    pruned by the exporter and put back, unused, so every graph has the same inputs.
    """
    import onnx
    from onnx import helper

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # deprecation notice of the TorchScript exporter
        torch.onnx.export(
            module,
            args,
            str(path),
            input_names=list(input_names),
            output_names=list(output_names),
            dynamic_axes=dynamic_axes,
            opset_version=opset,
            dynamo=DYNAMO,
            do_constant_folding=True,
        )
    m = onnx.load(str(path))
    present = {i.name: i for i in m.graph.input}
    if [n for n in input_names if n in present] != list(input_names):
        elem = helper.np_dtype_to_tensor_dtype(args[0].numpy().dtype)
        inputs = []
        for name, x in zip(input_names, args, strict=True):
            if name in present:
                inputs.append(present[name])
                continue
            dims = [("N" if dynamic_axes and d == 0 else int(n)) for d, n in enumerate(x.shape)]
            inputs.append(helper.make_tensor_value_info(name, elem, dims))
        del m.graph.input[:]
        m.graph.input.extend(inputs)
        onnx.save(m, str(path))


def _set_metadata(path: str | os.PathLike, metadata: Mapping[str, object]) -> None:
    import onnx

    m = onnx.load(str(path))
    del m.metadata_props[:]
    for k, v in metadata.items():
        m.metadata_props.add(key=str(k), value=v if isinstance(v, str) else json.dumps(v))
    onnx.checker.check_model(m)
    onnx.save(m, str(path))


def export_estimator(
    model: RobotModel,
    sensors: Sequence[str] | None,
    links: Sequence[str],
    kinds: Sequence[str],
    path: str | os.PathLike,
    dtype: torch.dtype = torch.float32,
    opset: int = DEFAULT_OPSET,
    gravity: Sequence[float] | None = None,
    rank_rtol: float | None = None,
    step_graph: bool = True,
) -> dict[str, str]:
    """Export the estimator of a robot, sensors and contact-slot layout as one ONNX graph.

    With ``step_graph`` a second file, ``<path stem>.step.onnx``, holds the same graph traced for
    exactly one frame (static shapes ``N = 1``): onnxruntime folds its shape arithmetic away,
    and :meth:`EstimatorRuntime.step <torchcontact.runtime.EstimatorRuntime.step>` uses it for
    single-frame latency while :meth:`~torchcontact.runtime.EstimatorRuntime.run` keeps the
    dynamic-batch graph.

    Args:
        model: the robot (any dtype; converted to ``dtype``).
        sensors: F/T sensor names (None: all of the model's).
        links: K link (or frame) names of the contact slots.
        kinds: K slot kinds, ``"wrench"``, ``"force"``, ``"force_dir"`` or ``"known"``.
        path: output ``.onnx`` file (weights and constants inside).
        dtype: ``torch.float32`` or ``torch.float64`` computation (and input/output) dtype.
        opset: ONNX opset version.
        gravity: ``(3,)`` gravity in the root frame, m/s^2 (fixed base; baked in); None keeps
            ``model.gravity``.
        rank_rtol: rank tolerance of the solve (None: :data:`torchcontact.solve.RANK_RTOL` of
            ``dtype``).
        step_graph: also write the single-frame graph ``<path stem>.step.onnx``.

    Returns:
        The metadata written into the file's ``metadata_props``.

    Raises:
        ValueError: an unknown sensor, link or kind, or a slot no sensor measures.

    Example:
        >>> import tempfile, torchcontact as tc
        >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> with tempfile.TemporaryDirectory() as d:
        ...     meta = export_estimator(m, None, ["hand_skin"], ["force"], f"{d}/est.onnx")
        >>> meta["robot"], json.loads(meta["slot_kinds"])
        ('tcarm', ['force'])
    """
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    for k in kinds:
        if k not in KINDS:
            raise ValueError(f"unknown kind {k!r}; expected one of {list(KINDS)}")
    m = model.to(dtype=dtype, device="cpu")
    if gravity is not None:
        m = m.with_gravity(gravity)
    est = ContactEstimator(m, sensors, rank_rtol=rank_rtol)
    graph = EstimatorGraph(est, links, kinds).eval()
    S, K = len(est.sensor_names), len(links)
    names_out = list(ESTIMATOR_OUTPUTS)
    dyn = {k: {0: "N"} for k in (*ESTIMATOR_INPUTS, *names_out)}
    _export(graph, _example_inputs(m, S, K), path, ESTIMATOR_INPUTS, names_out, dyn, opset)
    meta = estimator_metadata(m, est, links, kinds, opset, rank_rtol)
    if step_graph:
        step = step_graph_path(path)
        _export(
            graph, _example_inputs(m, S, K, n=1), step, ESTIMATOR_INPUTS, names_out, None, opset
        )
        meta["step_graph"] = step.name
        _set_metadata(step, {**meta, "batch": "1"})
    _set_metadata(path, meta)
    return meta


def step_graph_path(path: str | os.PathLike) -> Path:
    """The single-frame graph written beside an estimator graph: ``<stem>.step.onnx``."""
    p = Path(path)
    return p.with_name(f"{p.name.removesuffix('.onnx')}.step.onnx")


def export_residual(
    module: nn.Module,
    example_features: Tensor,
    path: str | os.PathLike,
    metadata: Mapping[str, object] | None = None,
    opset: int = DEFAULT_OPSET,
    example_state: Tensor | None = None,
) -> dict[str, str]:
    """Export a learned F/T residual model ``features (N, F) -> residual (N, 6)`` to ONNX.

    With ``example_state`` the module is recurrent: ``module(features, h_in) -> (residual,
    h_out)`` with ``h_in``, ``h_out`` shaped ``(N, H)``. The batch axis ``N`` is dynamic, the
    weights are stored inside the file and ``metadata`` goes to ``metadata_props`` (non-string
    values as JSON), with ``opset``, ``torch_version`` and ``sha256_weights`` added.

    Args:
        module: the model; exported in eval mode (its mode is restored afterwards).
        example_features: ``(N, F)`` example input (dtype of the export).
        path: output ``.onnx`` file.
        metadata: e.g. feature names and units, training run, sensor name.
        opset: ONNX opset version.
        example_state: ``(N, H)`` example recurrent state, or None for a stateless model.

    Returns:
        The metadata written.
    """
    was_training = module.training
    module.eval()
    try:
        if example_state is None:
            args, ins, outs = (example_features,), ["features"], ["residual"]
        else:
            args, ins = (example_features, example_state), ["features", "h_in"]
            outs = ["residual", "h_out"]
        dyn = {k: {0: "N"} for k in (*ins, *outs)}
        with torch.no_grad():
            _export(module, args, path, ins, outs, dyn, opset)
    finally:
        module.train(was_training)
    h = hashlib.sha256()
    for k, v in module.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    meta = {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in (metadata or {}).items()}
    meta.update(
        format="torchcontact.residual/1",
        opset=str(opset),
        torch_version=torch.__version__,
        sha256_weights=h.hexdigest(),
        features=str(int(example_features.shape[-1])),
        recurrent="true" if example_state is not None else "false",
    )
    _set_metadata(path, meta)
    return meta


class _ResidualStep(nn.Module):
    """One step of a recurrent residual with the state as explicit input and output.

    ``forward(features (N, F), h_in (N, L, H)) -> (residual (N, 6), h_out (N, L, H))``.
    """

    def __init__(self, module: nn.Module) -> None:
        super().__init__()
        self.module = module

    def forward(self, features: Tensor, h_in: Tensor) -> tuple[Tensor, Tensor]:
        """One frame of every batch element."""
        return self.module(features, h_in)


def export_residual_checkpoint(
    checkpoint: str | os.PathLike,
    path: str | os.PathLike,
    opset: int = DEFAULT_OPSET,
    check: bool = True,
) -> dict[str, str]:
    """Export a residual checkpoint directory (``python -m training``) to one ONNX file.

    The graph holds the weights and the feature/target normalisation (buffers of the module), has
    a dynamic batch axis and runs in float32: ``features (N, F) -> residual (N, 6)`` [N; N m],
    the F/T wrench ``[force; moment]`` to subtract from the sensor's reading. A GRU runs one frame
    per call with its state explicit: ``(features, h_in (N, L, H)) -> (residual, h_out)``, zeros
    for the first frame. ``metadata_props`` carry ``feature_names``, ``joint_names``, ``sensor``,
    ``units``, ``kind``, ``arch``, ``model_version`` (torchcontact version of the export),
    ``robot_sha256``, ``data_sha256`` (training data), ``checkpoint_weights_sha256`` and, from
    :func:`export_residual`, ``opset``, ``sha256_weights`` and ``recurrent``.

    Args:
        checkpoint: checkpoint directory (verified by :func:`load_residual_model`).
        path: output ``.onnx`` file.
        opset: ONNX opset version (the default loads in onnxruntime >= 1.14).
        check: run onnxruntime against torch on batch sizes 1 and 7 (``atol`` 1e-5).

    Returns:
        The metadata written.

    Raises:
        torchcontact.residual.CheckpointError: unreadable or tampered checkpoint.
        AssertionError: ``check`` found a difference.
    """
    from torchcontact import __version__
    from torchcontact.residual import ResidualGRU, load_residual_model

    module, meta = load_residual_model(checkpoint)
    F = module.in_features
    recurrent = isinstance(module, ResidualGRU)
    graph: nn.Module = _ResidualStep(module) if recurrent else module
    gen = torch.Generator().manual_seed(0)
    example = torch.randn(2, F, generator=gen)
    state = torch.zeros(2, module.layers, module.hidden) if recurrent else None
    info = {
        "feature_names": list(meta["features"]),
        "joint_names": list(meta.get("joint_names", [])),
        "sensor": meta.get("sensor", ""),
        "units": {
            "features": "q.<joint> rad or m, qd.<joint> per s, qdd.<joint> per s^2,"
            " other columns as logged",
            "residual": "[N; N m] wrench [force; moment] in the sensor frame, subtracted from the"
            " reading",
        },
        "kind": module.kind,
        "arch": module.arch,
        "model_version": __version__,
        "robot_sha256": meta.get("robot_sha256", ""),
        "data_sha256": meta.get("data_sha256", ""),
        "checkpoint_weights_sha256": meta.get("weights_sha256", ""),
        "dtype": "float32",
    }
    if recurrent:
        info["state_shape"] = ["N", module.layers, module.hidden]
    out = export_residual(graph, example, path, info, opset, state)
    if check:
        for n in (1, 7):
            ins = [torch.randn(n, F, generator=gen)]
            if recurrent:
                ins.append(torch.randn(n, module.layers, module.hidden, generator=gen))
            check_parity(graph, path, ins, atol=1e-5)
    return out


def check_parity(
    module: nn.Module,
    path: str | os.PathLike,
    inputs: Sequence[Tensor] | Tensor,
    atol: float = 1e-5,
) -> float:
    """Run the module and the ONNX file on the same inputs; raise if they differ by > ``atol``.

    Args:
        module: the torch module (run in eval mode, no grad).
        path: the exported ``.onnx`` file.
        inputs: one tensor or a sequence, in the graph's input order.
        atol: maximum absolute difference allowed on every output.

    Returns:
        The maximum absolute difference over all outputs.

    Raises:
        AssertionError: a difference above ``atol``, or a shape mismatch.
    """
    import onnxruntime as ort

    ins = [inputs] if isinstance(inputs, Tensor) else list(inputs)
    was_training = module.training
    module.eval()
    try:
        with torch.no_grad():
            ref = module(*ins)
    finally:
        module.train(was_training)
    ref = [ref] if isinstance(ref, Tensor) else list(ref)
    sess = ort.InferenceSession(str(Path(path)), providers=["CPUExecutionProvider"])
    feed = {i.name: x.detach().cpu().numpy() for i, x in zip(sess.get_inputs(), ins, strict=True)}
    got = sess.run(None, feed)
    err = 0.0
    for r, o in zip(ref, got, strict=True):
        r = r.detach().cpu().numpy()
        if r.shape != o.shape:
            raise AssertionError(f"shape mismatch: torch {r.shape}, onnx {o.shape}")
        if r.size:
            err = max(err, float(np.max(np.abs(r.astype(np.float64) - o.astype(np.float64)))))
    if not err <= atol:
        raise AssertionError(f"ONNX output differs from torch by {err:.3g} > atol {atol:.3g}")
    return err
