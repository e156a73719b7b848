"""Export the contact estimator and F/T corrections to ONNX (extra ``export``).

:func:`export_estimator` writes the *whole* estimator of one robot, sensor set and contact-slot
layout (RNEA forward pass, ``b``, the contact maps, the minimum-norm solve by pivoted Cholesky of
:mod:`torchcontact.solve`, the backward pass, the status checks; optionally the moving base, the
torque-sensor rows, the covariance and a chained residual correction) as two ONNX graphs with the
same metadata, run with onnxruntime alone through :mod:`torchcontact.runtime`:

* ``<name>.onnx``, the **batched** graph: the estimator program of
  :mod:`torchcontact.estimation.programs` emitted one node per scalar operation, each node running
  over the ``N`` frames (throughput). Inputs (``N`` dynamic, ``S`` sensors, ``K`` slots)::

      q, qd, qdd     (N, nv)   joint positions (rad, m), velocities, accelerations
      ft             (N, S, 6) readings [force N; moment N m], sensor frame and direction
      ft_residual    (N, S, 6) subtracted from ft (zeros: no correction)
      positions      (N, K, 3) contact points in the slot's link frame, m
      active         (N, K)    1 where the slot is in contact, 0 elsewhere
      directions     (N, K, 3) force directions of force_dir slots (link frame)
      wrenches       (N, K, 6) given wrenches of known slots (link frame, about the point)
      omega, domega, proper_acc (N, 3)  base IMU (``moving_base``)
      tau_measured, tau_mask (N, nv)    measured joint torques and their 0/1 validity
      ft_cov         (N, S, 6, 6)       reading noise covariance (``covariance``)
      extra (N, E), h_in.<sensor> (N, L, H)   inputs of chained residual corrections

  Outputs: ``force, moment (N, K, 3)``, ``joint_torques (N, nv)``, ``rank, unknowns (N, S)``
  int64, ``residual (N, S)``, ``status (N,)`` int64 (bits of :data:`torchcontact.STATUS`;
  outputs of such frames are NaN), ``covariance (N, K, 6, 6)``, ``h_out.<sensor>``.
* ``<name>.step.onnx``, the **single-frame** graph (:mod:`torchcontact.onnx.step`): the same
  function for one frame as a few hundred nodes vectorised over bodies and slots (latency), with
  one packed input ``x (1, F)`` and one packed output ``out (1, O)`` whose layouts are in the
  metadata (``step_inputs``, ``step_outputs``: field -> [offset, shape]). With ``localize``
  it also localizes the contact of one link's ``force`` slot from its sensor's wrench and
  collision mesh (:mod:`torchcontact.onnx.step.localize`; outputs ``localize_status``,
  ``localize_position``).

:func:`export_residual_checkpoint` writes a correction stack (:mod:`torchcontact.residual`:
offset, re-identified inertial parameters, learned layer) as one graph from raw joint state to
the correction ``(N, 6)``; :func:`export_residual` writes any ``nn.Module`` mapping features
``(N, F)`` to an F/T residual ``(N, 6)`` (optionally with a recurrent state ``h_in -> h_out``);
:func:`check_parity` compares a file with its module.

With ``constraints`` (:class:`~torchcontact.FrictionCones`) :func:`export_estimator` writes the
friction-cone constrained estimator instead: its program emitted like the batched graph, the
interior-point iterations one ONNX ``Loop`` (one batched graph, no single-frame
graph: :meth:`EstimatorRuntime.step <torchcontact.runtime.EstimatorRuntime.step>` runs it with
``N = 1``). It takes :data:`CONE_INPUTS` after the fixed-base inputs (``normals (N, K, 3)``
outward surface normals, link frame; ``friction (N, K)`` coefficients; ``pushing (N, K)`` 1/0)
and returns :data:`CONE_OUTPUTS` after the outputs (``converged (N, S)`` bool,
``iterations (N, S)`` int64, ``cone_active (N, K)`` bool).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from torchcontact.constrained import FrictionCones
from torchcontact.contacts import KINDS
from torchcontact.errors import InputError
from torchcontact.estimation import ContactEstimator
from torchcontact.model import RobotModel
from torchcontact.onnx import format as fmt
from torchcontact.onnx.format import (
    CONE_INPUTS,
    CONE_OUTPUTS,
    ESTIMATOR_FORMAT,
    ESTIMATOR_INPUTS,
    ESTIMATOR_OUTPUTS,
    RESIDUAL_FORMAT,
    RESIDUAL_GRAPH_FORMAT,
    Key,
)

__all__ = [
    "CONE_INPUTS",
    "CONE_OUTPUTS",
    "ESTIMATOR_INPUTS",
    "ESTIMATOR_OUTPUTS",
    "check_parity",
    "export_estimator",
    "export_residual",
    "export_residual_checkpoint",
    "step_graph_path",
    "RESIDUAL_GRAPH_FORMAT",
]

#: Format of the metadata written by :func:`export_estimator` (the runtime's name for it).
FORMAT = ESTIMATOR_FORMAT
DEFAULT_OPSET = 18


def _write(gb, path: str | os.PathLike, metadata: Mapping[str, object], opset: int) -> None:
    """Write a builder's graph with its metadata (checked, published atomically)."""
    import onnx

    m = gb.model(fmt.encode(metadata))
    m.opset_import[0].version = opset
    onnx.checker.check_model(m)
    _save_atomic(m, Path(path))


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
    *,
    moving_base: bool = False,
    torque_rows: bool = False,
    covariance: bool = False,
    velocity_margin: float | None = None,
    ft_range: Mapping[str, float | Sequence[float]] | None = None,
    residual: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
    joints: Sequence[str] | str | None = None,
    constraints: FrictionCones | None = None,
    online: bool | Mapping[str, str] = False,
    ft_noise: Mapping[str, Sequence[float] | str] | Sequence[str] | None = None,
    localize: str | None = None,
    meshes: Any = None,
    localize_threshold: float = 1.0,
    localize_max_faces: int | None = None,
) -> dict[str, str]:
    """Export the estimator of a robot, sensors and contact-slot layout as ONNX graphs.

    Writes ``path`` (the batched graph) and, with ``step_graph``, ``<path stem>.step.onnx`` (the
    single-frame graph); see the module docstring for their inputs and outputs. Both compute
    :meth:`ContactEstimator.estimate <torchcontact.ContactEstimator.estimate>` (same program,
    same pivots and rank rule), run in float32 or float64 in onnxruntime, and carry the same
    ``metadata_props``: robot, URDF sha256, joint names, sensors, slots, units, flags, layouts,
    versions.

    Args:
        model: the robot (any dtype; converted to ``dtype``).
        sensors: F/T sensor names (None: all of the model's).
        links: K link (or frame) names of the contact slots.
        kinds: K slot kinds, ``"wrench"``, ``"force"``, ``"force_dir"`` or ``"known"``.
        path: output ``.onnx`` file (constants inside).
        dtype: ``torch.float32`` or ``torch.float64`` computation (and input/output) dtype.
        opset: ONNX opset version (>= 18).
        gravity: ``(3,)`` gravity in the root frame, m/s^2 (fixed base); None keeps
            ``model.gravity``.
        rank_rtol: rank tolerance of the solve (None: :data:`torchcontact.solve.RANK_RTOL` of
            ``dtype``).
        step_graph: also write the single-frame graph ``<path stem>.step.onnx``.
        moving_base: inputs ``omega, domega, proper_acc`` (an IMU on the root body) instead of a
            fixed base with ``model.gravity``.
        torque_rows: inputs ``tau_measured, tau_mask``: measured joint torques add equations.
        covariance: input ``ft_cov``, output ``covariance`` (first-order propagation).
        velocity_margin: status bit 64 above this multiple of the URDF velocity limits.
        ft_range: sensor -> measuring range (status bit 64 beyond it).
        residual: residual-correction graph(s) (``python -m export residual``, or a correction
            stack graph) chained into both graphs: they then take the raw readings plus the
            corrections' ``extra`` inputs (and recurrent states).
        joints: the joints whose torques to output (the others are NaN): None (all), names, or
            ``"sensed"``, the joints whose torque the sensors determine (inside the sensors'
            subtrees, and between a sensor and the next moving joint towards the root). The
            single-frame graph keeps only the bodies the regions and these torques need.
        constraints: :class:`~torchcontact.FrictionCones`: the friction-cone constrained
            estimator instead (its program, the iterations one ONNX ``Loop``; one batched graph,
            more inputs and outputs, see the module docstring; metadata ``constraints``); fixed
            base and F/T rows only.
        online: True, or sensor -> the link payloads attach to (default: the deepest body of
            its subtree): the single-frame graph takes each sensor's offset ``bias (S, 6)`` and
            inertial change ``theta.<sensor>`` as inputs and returns ``ft_model (S, 6)`` and
            ``regressor.<sensor> (6, 10)`` (:mod:`torchcontact.onnx.step.online`; the runtime's
            bias tracking, ``tare``, payloads); a correction stack's offset and inertial layers
            become their defaults (metadata ``online``). The batched graph is unchanged.
        ft_noise: every sensor's reading noise, ``{sensor: (6,) standard deviations [N; N m],
            (2,) SIGMA_F, SIGMA_M or a driver profile name}`` or ``--ft-noise`` strings
            (:func:`torchcontact.logs.noise.fixed_noise`): both graphs solve weighted by it,
            as :meth:`ContactEstimator.estimate <torchcontact.ContactEstimator.estimate>` with
            ``ft_covariance = diag(std^2)`` (constants in the graphs; metadata ``ft_noise``).
            None: the paper's unweighted ``pinv(A) b``.
        localize: a link with a ``force`` slot: the single-frame graph localizes the contact
            on it from its region's ``b`` and its collision mesh in steps whose input has no
            active slot in that region, and uses it as the slot's contact (outputs
            ``localize_status``, ``localize_position``; metadata ``localize``;
            :mod:`torchcontact.onnx.step.localize`). The batched graph is unchanged.
        meshes: with ``localize``, the robot's collision meshes
            (:func:`torchcontact.meshes.load_meshes`) or a mapping link -> ``LinkMesh``.
        localize_threshold: with ``localize``, the force below which a step has no contact, N.
        localize_max_faces: with ``localize``, above this many faces the graph carries the
            mesh's convex hull (None:
            :data:`~torchcontact.onnx.step.localize.DEFAULT_MAX_FACES`).

    Returns:
        The metadata written into the files' ``metadata_props``.

    Raises:
        ValueError: an unknown sensor, link or kind, a slot no sensor measures, a bad option.
        InputError: an ``ft_noise`` that is not > 0, for a sensor the estimator lacks, or
            missing a sensor.
        ModelMismatchError: a residual graph made for another robot, joint set or sensor.

    Example:
        >>> import tempfile, torchcontact as tc
        >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> with tempfile.TemporaryDirectory() as d:
        ...     meta = export_estimator(m, None, ["hand_skin"], ["force"], f"{d}/est.onnx")
        >>> meta["robot"], json.loads(meta["slot_kinds"])
        ('tcarm', ['force'])
    """
    import onnx

    from torchcontact import __version__
    from torchcontact.online.state import sensor_layouts
    from torchcontact.onnx.batched import (
        batched_graph,
        constrained_graph,
        load_residual_graphs,
        residual_meta,
    )
    from torchcontact.onnx.builder import OPSET
    from torchcontact.onnx.step import build_step_graph
    from torchcontact.onnx.step import online as online_stage

    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    for k in kinds:
        if k not in KINDS:
            raise InputError(f"unknown kind {k!r}; expected one of {list(KINDS)}")
    if opset < OPSET:
        raise ValueError(f"opset must be >= {OPSET}, got {opset}")
    m = model.to(dtype=dtype, device="cpu")
    if gravity is not None:
        m = m.with_gravity(gravity)
    est = ContactEstimator(
        m, sensors, rank_rtol=rank_rtol, velocity_margin=velocity_margin, ft_range=ft_range
    )
    loc = None
    if localize is not None:
        from torchcontact.onnx.step.localize import DEFAULT_MAX_FACES, localize_link

        if constraints is not None or not step_graph:
            raise InputError("localize: the localization is the single-frame graph's (step_graph;"
                             " not with constraints)")  # fmt: skip
        max_faces = localize_max_faces or DEFAULT_MAX_FACES
        loc = localize_link(m, est.layout((), ()), links, kinds, localize, meshes,
                            localize_threshold, max_faces)  # fmt: skip
    em = est.layout(tuple(links), tuple(kinds))
    res = load_residual_graphs(residual, m, est.sensor_names)
    noise = None
    if ft_noise is not None:
        if torque_rows:
            raise InputError(
                "ft_noise with torque_rows: the torque rows' noise is not known (a weighted"
                " estimate needs every row's noise); export one or the other"
            )
        from torchcontact.noise import fixed_noise

        ftn = fixed_noise(ft_noise, est.sensor_names, list(m.ft_sensors))
        noise = tuple(ftn.sensors[s].std for s in est.sensor_names)
    npd = np.dtype(str(dtype).removeprefix("torch."))
    flags = (bool(moving_base), bool(torque_rows), bool(covariance))
    path = Path(path)
    step = step_graph_path(path)
    coords = em.torque_joints(joints)
    if online and not step_graph:
        raise InputError("online: the online inputs are the single-frame graph's (step_graph)")
    if constraints is not None:
        if any(flags) or res or joints is not None or online:
            raise InputError(
                "constraints: the constrained graph takes the fixed-base F/T inputs only (no"
                " moving_base, torque_rows, covariance, residual, joints or online)"
            )
        cones = constraints.program_flags(m.dtype)  # the objective's prior included
        gb, shapes = constrained_graph(em, cones, npd, noise)
        outputs = [*ESTIMATOR_OUTPUTS, *CONE_OUTPUTS]
    else:
        gb, shapes = batched_graph(em, flags, npd, res, coords, noise)
        outputs = [*ESTIMATOR_OUTPUTS, *(["covariance"] if covariance else [])]
    meta = {
        Key.FORMAT: FORMAT,
        Key.ROBOT: m.name,
        Key.URDF_SHA256: m.urdf_sha256,
        Key.ROBOT_IDENTITY_SHA256: m.identity.sha256,
        Key.ROBOT_IDENTITY: m.identity.to_json(),
        Key.JOINT_NAMES: list(m.joint_names),
        Key.SENSORS: [
            {"name": s.name, "joint": s.joint, "frame": s.frame, "direction": s.measure_direction}
            for s in est.sensors
        ],
        Key.SLOT_LINKS: list(links),
        Key.SLOT_KINDS: list(kinds),
        Key.INPUTS: list(shapes),
        Key.INPUT_SHAPES: shapes,
        Key.OUTPUTS: outputs,
        Key.UNITS: {
            **{i.name: i.unit for i in fmt.INPUTS},
            "force": "N",
            "moment": "N m",
            "joint_torques": "N m or N",
            "gravity": "m/s^2",
        },
        Key.FRAMES: "positions, directions, wrenches, force, moment: the slot's link frame; "
        "moments about the contact point; ft: each sensor's declared frame and direction; "
        "omega, domega, proper_acc: the root body's frame",
        Key.GRAVITY: [float(g) for g in m.gravity],
        Key.DTYPE: str(npd),
        Key.MOVING_BASE: flags[0],
        Key.TORQUE_ROWS: flags[1],
        Key.COVARIANCE: flags[2],
        Key.VELOCITY_MARGIN: velocity_margin,
        Key.FT_RANGE: {
            k: np.broadcast_to(np.asarray(v, float), (6,)).tolist()
            for k, v in (ft_range or {}).items()
        },
        Key.SOLVER: "pivoted cholesky (torchcontact.solve); step graph: Gauss-Jordan form",
        Key.RANK_RTOL: repr(float(em.rank_rtol)),
        Key.TORQUE_JOINTS: [m.joint_names[c] for c in coords],
        Key.RESIDUALS: residual_meta(res),
        Key.BATCHED_GRAPH: path.name,
        Key.STEP_GRAPH: step.name if step_graph and constraints is None else "",
        Key.VERSION: __version__,
        Key.TORCH_VERSION: torch.__version__,
        Key.OPSET: str(opset),
        Key.STEP_INPUTS: {},
        Key.STEP_OUTPUTS: {},
    }
    graphs = [(gb.model(), path, "batched")]
    if constraints is not None:
        iterations, eps, tol, _, prior = cones
        objective = constraints.objective_of(m.dtype)
        meta[Key.CONSTRAINTS] = {"iterations": iterations, "eps": eps, "tol": tol,
                                 "objective": objective, "prior": prior}  # fmt: skip
        meta[Key.SOLVER] = (
            f"friction-cone constrained estimate ({objective}, torchcontact.constrained),"
            " one ONNX Loop"
        )
    elif step_graph:
        layouts = []
        if online:
            links = online if isinstance(online, Mapping) else None
            defaults = online_stage.stack_defaults(m, res, est.sensor_names)
            layouts = sensor_layouts(m, est.sensor_names, links, *defaults)
            meta[Key.ONLINE] = [lay.to_json(m.body_names) for lay in layouts]
            meta[Key.SLOT_REGIONS] = [sl.region for sl in em.slots]
        sm, lin, lout = build_step_graph(em, *flags, dtype=npd, residuals=res, coords=coords,
                                         online=layouts, noise=noise, localize=loc)  # fmt: skip
        if loc is not None:
            k = next(i for i, s in enumerate(em.slots) if (s.link, s.kind) == (loc.link, "force"))
            meta[Key.LOCALIZE] = {
                "graph": "step (the batched graph does not localize)",
                "link": loc.link,
                "slot": k,
                "region": em.slots[k].region,
                "sensor": est.sensor_names[em.slots[k].region],
                "force_threshold": loc.force_threshold,
                "mesh": loc.mesh_choice,
                "faces": len(loc.mesh.faces),
                "outputs": {
                    "localize_status": "bits of torchcontact.status.LocalizeStatus (2 no"
                    " contact, 4 no intersection, 32 skin contact in the region); NaN where"
                    " the step's status is not 0",
                    "localize_position": "the localized contact point, link frame, m; NaN"
                    " where not used",
                },
            }
        meta[Key.STEP_INPUTS] = lin.as_dict()
        meta[Key.STEP_OUTPUTS] = lout.as_dict()
        graphs.append((sm, step, "step"))
    if noise is not None:  # only then: an unweighted export stays as it was
        meta[Key.FT_NOISE] = ftn.summary()
        meta[Key.SOLVER] += "; noise-weighted (ft_noise, whitened rows)"
    written = fmt.encode(meta)
    for gm, p, kind in graphs:
        gm.opset_import[0].version = opset
        del gm.metadata_props[:]
        for k, v in {**written, Key.GRAPH: kind}.items():
            gm.metadata_props.add(key=k, value=v)
        onnx.checker.check_model(gm)
        _save_atomic(gm, p)
    return {**written, Key.GRAPH: "batched"}


def _save_atomic(model, path: Path) -> None:
    """Write an ONNX model beside ``path`` under a temporary name, then rename it into place."""
    import onnx

    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        onnx.save(model, str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


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

    The graph is written by the builder from the module's ``torch.fx`` graph (``nn.Linear``,
    ``nn.GRUCell``, ``Tanh``/``Sigmoid``/``ReLU``/``SiLU``, elementwise arithmetic,
    ``torch.cat``); another operation is refused with an :class:`InputError` naming it.

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

    Raises:
        InputError: the module uses an operation the builder does not emit.
    """
    from torchcontact.onnx.builder import GraphBuilder
    from torchcontact.onnx.networks import emit_module

    gb = GraphBuilder(example_features.detach().cpu().numpy().dtype, "torchcontact_residual")
    ins = [gb.input("features", ["N", int(example_features.shape[-1])])]
    if example_state is not None:
        ins.append(gb.input("h_in", ["N", *map(int, example_state.shape[1:])]))
    was_training = module.training
    module.eval()
    try:
        with torch.no_grad():
            outs = emit_module(gb, module, ins)
    except ValueError as e:
        raise InputError(f"export_residual: {e}") from None
    finally:
        module.train(was_training)
    names = ["residual", "h_out"] if example_state is not None else ["residual"]
    if len(outs) != len(names):
        raise InputError(f"export_residual: the module returns {len(outs)} values, not {names}")
    for o, name in zip(outs, names, strict=True):
        gb.op("Identity", o, out=name)
        gb.output(name, ["N", "R" if name == "residual" else "H"])
    h = hashlib.sha256()
    for k, v in module.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    meta = fmt.encode(dict(metadata or {}))
    meta.update(
        format=RESIDUAL_FORMAT,
        opset=str(opset),
        torch_version=torch.__version__,
        sha256_weights=h.hexdigest(),
        features=str(int(example_features.shape[-1])),
        recurrent="true" if example_state is not None else "false",
    )
    _write(gb, path, meta, opset)
    return meta


class _CorrectionInputs(nn.Module):
    """A :class:`~torchcontact.residual.CorrectionGraph` with its optional inputs made positional.

    ``forward(q, qd, qdd[, extra][, h_in]) -> correction[, h_out]``.
    """

    def __init__(self, graph: nn.Module, has_extra: bool, recurrent: bool) -> None:
        super().__init__()
        self.graph, self.has_extra, self.recurrent = graph, has_extra, recurrent

    def forward(self, *args: Tensor) -> Tensor | tuple[Tensor, Tensor]:
        """Correction ``(N, 6)`` (and the next GRU state)."""
        q, qd, qdd = args[:3]
        extra = args[3] if self.has_extra else None
        h_in = args[-1] if self.recurrent else None
        c, h_out = self.graph(q, qd, qdd, extra, h_in)
        return (c, h_out) if self.recurrent else c


def export_residual_checkpoint(
    checkpoint: str | os.PathLike,
    path: str | os.PathLike,
    robot: RobotModel | str | os.PathLike | None = None,
    opset: int = DEFAULT_OPSET,
    check: bool = True,
) -> dict[str, str]:
    """Export a correction checkpoint (``python -m training``) as one ONNX graph.

    The graph is the whole stack, computed from raw inputs inside it: the RNEA forward pass and
    the sensor's inertial regressor (nominal wrench and inertial layer), the offset, the
    learned layer's features (sin/cos, velocities, nominal wrench, extra columns) with their
    normalisation, and the network. It runs in float32 with a dynamic batch ``N``::

        q, qd, qdd  (N, nv)     joint state in the robot's joint order (metadata joint_names)
        extra       (N, E)      the extra columns (metadata extra_columns), when E > 0
        h_in        (N, L, H)   GRU state (zeros at the start), GRU stacks only
        -> correction (N, 6)    [N; N m], sensor frame: subtract it from the sensor's reading
           h_out      (N, L, H) the next GRU state (one frame per call)

    ``metadata_props``: ``format`` (:data:`RESIDUAL_GRAPH_FORMAT`), ``inputs``,
    ``input_shapes``, ``outputs``, ``units``, ``joint_names``, ``sensor``, ``robot``,
    ``robot_sha256``, ``layers``, ``extra_columns``, ``feature_names``, ``recurrent`` (and
    ``state_shape``), ``inertial`` (rank), ``data_sha256``, ``checkpoint_weights_sha256``,
    ``model_version``, ``torch_version``, ``dtype``, ``opset``, ``sha256_weights``.

    Args:
        checkpoint: checkpoint directory (verified by
            :meth:`~torchcontact.residual.ResidualCorrection.load`).
        path: output ``.onnx`` file.
        robot: the robot (a model or URDF path); None: the URDF recorded at training
            (``checkpoint.json["urdf"]``), which must still hash the same.
        opset: ONNX opset version.
        check: compare onnxruntime with torch (float32) on batches of 1 and 7 frames
            (``atol`` 1e-4 N).

    Returns:
        The metadata written.

    Raises:
        CheckpointError: unreadable, tampered or foreign checkpoint, another robot, or no robot
            to build the graph from.
        AssertionError: ``check`` found a difference.
    """
    from torchcontact import __version__
    from torchcontact.errors import InputError
    from torchcontact.residual import META_FILE, ResidualCorrection

    if robot is None:
        try:
            recorded = json.loads((Path(checkpoint) / META_FILE).read_text()).get("urdf")
        except (OSError, json.JSONDecodeError):
            recorded = None
        if not recorded or not Path(recorded).is_file():
            raise InputError(
                f"{checkpoint}: no robot given and the URDF recorded at training ({recorded}) is"
                " not available: pass the robot's URDF (--urdf or --robot)"
            )
        robot = recorded
    model = robot if isinstance(robot, RobotModel) else RobotModel.from_urdf(robot)
    model = model.to("cpu", torch.float32)
    corr = ResidualCorrection.load(checkpoint, model)
    graph = corr.graph.eval()
    E = len(corr.extra_columns)
    learned = corr.learned
    recurrent = corr.recurrent
    wrapper = _CorrectionInputs(graph, E > 0, recurrent).eval()
    nv = model.nv
    ins = ["q", "qd", "qdd"] + (["extra"] if E else []) + (["h_in"] if recurrent else [])
    outs = ["correction"] + (["h_out"] if recurrent else [])
    gen = torch.Generator().manual_seed(0)

    def example(n: int) -> list[Tensor]:
        x = [torch.rand(n, nv, generator=gen) * 2 - 1 for _ in range(3)]
        if E:
            x.append(torch.rand(n, E, generator=gen) * 10 + 25)
        if recurrent:
            x.append(torch.randn(n, learned.layers, learned.hidden, generator=gen))  # type: ignore[union-attr]
        return x

    shapes: dict[str, list] = {"q": ["N", nv], "qd": ["N", nv], "qdd": ["N", nv]}
    if E:
        shapes["extra"] = ["N", E]
    if recurrent:
        shapes["h_in"] = ["N", learned.layers, learned.hidden]  # type: ignore[union-attr]
    gb = _correction_graph(model, corr, shapes)
    h = hashlib.sha256()
    for k, v in sorted(corr.tensors().items()):
        h.update(k.encode())
        h.update(v.numpy().tobytes())
    info = corr.describe()
    meta: dict[str, object] = {
        Key.FORMAT: RESIDUAL_GRAPH_FORMAT,
        "inputs": ins,
        "input_shapes": shapes,
        "outputs": outs,
        "units": {
            "q": "rad or m",
            "qd": "rad/s or m/s",
            "qdd": "rad/s^2 or m/s^2",
            "extra": "as logged (see extra_columns)",
            "correction": "[N, N, N, N m, N m, N m] wrench [force; moment] in the sensor frame"
            " and measure direction: subtract it from the reading",
        },
        "joint_names": list(model.joint_names),
        "sensor": corr.sensor,
        "robot": model.name,
        Key.ROBOT_SHA256: model.urdf_sha256,
        Key.ROBOT_IDENTITY_SHA256: model.identity.sha256,
        Key.ROBOT_IDENTITY: model.identity.to_json(),
        "layers": corr.layers,
        "extra_columns": corr.extra_columns,
        "feature_names": info.get("learned", {}).get("feature_names", []),
        "recurrent": "true" if recurrent else "false",
        "inertial": {k: v for k, v in info.get("inertial", {}).items() if k != "singular_values"},
        "data_sha256": corr.meta.get("data_sha256", ""),
        "checkpoint_weights_sha256": corr.meta.get("weights_sha256", ""),
        "model_version": __version__,
        "torch_version": torch.__version__,
        "dtype": "float32",
        "opset": str(opset),
        "sha256_weights": h.hexdigest(),
    }
    if recurrent:
        meta["state_shape"] = ["N", learned.layers, learned.hidden]  # type: ignore[union-attr]
    meta.update(_stack_parts(corr, opset))
    written = fmt.encode(meta)
    _write(gb, path, written, opset)
    if check:
        for n in (1, 7):
            check_parity(wrapper, path, example(n), atol=1e-4)
    return written


def _stack_parts(corr, opset: int) -> dict[str, object]:
    """The stack's layers as data, so that an estimator's step graph can rebuild them natively.

    ``stack``: ``offset`` (6 values or None), ``inertial_bodies`` and ``delta`` (the inertial
    layer's bodies and their ten parameters each, :data:`torchcontact.residual.PARAM_NAMES`, link
    frame), ``features`` (the learned layer's :class:`~torchcontact.residual.FeatureSpec`) and
    ``learned`` (its kind). ``learned_graph``: the learned layer alone (``features (N, F)`` [and
    ``h_in``] -> ``residual (N, 6)`` [and ``h_out``], float32) as a base64 ONNX model. The
    single-frame estimator graph computes the physics layers from its own forward pass (a few
    nodes instead of the thousands of the stack's own forward pass) and inlines only the network.
    """
    import base64

    from torchcontact.onnx.builder import GraphBuilder
    from torchcontact.onnx.networks import emit_learned

    out: dict[str, object] = {Key.STACK: corr.spec.to_json()}
    net = corr.learned
    if net is not None:
        gb = GraphBuilder(np.float32, "torchcontact_learned")
        x = gb.input("features", ["N", net.in_features])
        h = gb.input("h_in", ["N", net.layers, net.hidden]) if corr.recurrent else None
        r, h_out = emit_learned(gb, net, x, h)
        gb.op("Identity", r, out="residual")
        gb.output("residual", ["N", 6])
        if h_out is not None:
            gb.op("Identity", h_out, out="h_out")
            gb.output("h_out", ["N", net.layers, net.hidden])
        m = gb.model()
        m.opset_import[0].version = opset
        out[Key.LEARNED_GRAPH] = base64.b64encode(m.SerializeToString()).decode()
    return out


def _correction_graph(model: RobotModel, corr, shapes: dict[str, list]):
    """The whole correction stack from raw joint state, float32, through the builder.

    The physics layers are :func:`~torchcontact.onnx.networks.correction_program` emitted over
    ``N`` frames; the learned layer's features are one selection from ``[q, qd, qdd, extra,
    sin q, cos q, nominal]``, its network :func:`~torchcontact.onnx.networks.emit_learned`.
    """
    from torchcontact.onnx.builder import GraphBuilder, emit_program
    from torchcontact.onnx.networks import correction_program, emit_learned, feature_matrix

    gb = GraphBuilder(np.float32, "torchcontact_correction")
    for name, sh in shapes.items():
        gb.input(name, sh)
    n = gb.op("Slice", gb.op("Shape", "q"), gb.i([0]), gb.i([1]))
    phys, nominal = gb.fresh("physics"), gb.fresh("nominal")
    prog = correction_program(model, corr.spec)
    emit_program(gb, prog, {"q": "q", "qd": "qd", "qdd": "qdd"},
                 {"physics": phys, "nominal": nominal}, n)  # fmt: skip
    c, h_out = phys, None
    if corr.learned is not None:
        parts = ["q", "qd", "qdd", *(["extra"] if "extra" in shapes else [])]
        src = gb.op("Concat", *parts, gb.op("Sin", "q"), gb.op("Cos", "q"), nominal, axis=1)
        sel = feature_matrix(model, corr.features, corr.extra_columns)
        feats = gb.op("MatMul", src, gb.f(sel))
        r, h_out = emit_learned(gb, corr.learned, feats, "h_in" if corr.recurrent else None)
        c = gb.op("Add", c, r)
    gb.op("Identity", c, out="correction")
    gb.output("correction", ["N", 6])
    if h_out is not None:
        gb.op("Identity", h_out, out="h_out")
        gb.output("h_out", shapes["h_in"])
    return gb


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
