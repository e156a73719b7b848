"""Run an exported contact estimator with onnxruntime and numpy only (no torch import).

:func:`torchcontact.export.export_estimator` (``python -m export estimator ...``) writes two graphs
of one robot, sensor set and slot layout, with the same ``metadata_props``:

* ``<name>.onnx``, the **batched** graph: named inputs ``(N, ...)``, one node per scalar operation
  of the estimator program, each running over the ``N`` frames (throughput, :meth:`run`);
* ``<name>.step.onnx``, the **single-frame** graph: one packed input vector and one packed output
  vector (layouts in the metadata), every stage vectorised over bodies and slots, a few hundred
  nodes (latency, :meth:`step`).

Both take the raw reading when a residual correction is chained into them (``--residual`` at
export), or :class:`EstimatorRuntime` chains a separate correction graph (``residual=``); either
way one call goes from the raw reading to the estimate. :class:`ResidualGraph` is the one place
that knows the correction graphs' interfaces.

:meth:`EstimatorRuntime.step` and :meth:`EstimatorRuntime.run` take one :class:`Inputs` value
(or a mapping) holding the inputs by their names (:data:`torchcontact.onnx.format.INPUTS`; the
older spellings are accepted); a new input of a graph is one more name, not one more parameter.

Example:
    >>> rt = EstimatorRuntime("tcarm.onnx", robot="tcarm")  # doctest: +SKIP
    >>> out = rt.step(Inputs(q=q, qd=qd, qdd=qdd, ft=ft, positions=p))  # doctest: +SKIP
    >>> out["force"].shape  # (K, 3), N, in each slot's link frame  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from torchcontact.errors import InputError, ModelMismatchError
from torchcontact.identity import RobotIdentity
from torchcontact.onnx import format as fmt
from torchcontact.onnx.format import (
    ESTIMATOR_FORMAT,
    RESIDUAL_FORMAT,
    RESIDUAL_FORMATS,
    Key,
)

__all__ = [
    "EstimatorRuntime",
    "Inputs",
    "ModelMismatchError",
    "ResidualGraph",
    "robot_identity",
    "session_options",
]

#: Format of the estimator graphs this runtime reads (``metadata_props["format"]``).
FORMAT = ESTIMATOR_FORMAT
#: The positional order of :meth:`EstimatorRuntime.step` and ``run`` of earlier versions.
_POSITIONAL = ("q", "qd", "qdd", "ft", "positions", "active", "directions", "wrenches",
               "ft_residual")  # fmt: skip


@dataclass
class Inputs:
    """The inputs of one frame (:meth:`EstimatorRuntime.step`) or of ``N`` (``run``), by name.

    Every field is optional here; the graph says which it needs (a missing required one is an
    :class:`~torchcontact.errors.InputError` naming it), the others default to zeros
    (``active`` and ``pushing`` to ones, ``tau_mask`` to the finite entries of
    ``tau_measured``). Shapes per frame (``run`` adds a leading ``N``); names, units and frames in
    :data:`torchcontact.onnx.format.INPUTS`.

    Attributes:
        q: ``(nv,)`` joint positions, rad or m. ``qd``, ``qdd`` likewise.
        ft: ``(S, 6)`` raw readings ``[N; N m]``, or sensor name -> ``(6,)``.
        positions: ``(K, 3)`` contact points, link frames, m.
        active: ``(K,)`` 1/0 slot activity.
        directions: ``(K, 3)`` force directions of ``force_dir`` slots.
        wrenches: ``(K, 6)`` wrenches of ``known`` slots.
        ft_residual: ``(S, 6)`` a further correction subtracted from ``ft``.
        omega: ``(3,)`` base angular velocity, rad/s (moving base); ``domega``, ``proper_acc``.
        tau_measured: ``(nv,)`` measured joint torques (torque rows); ``tau_mask`` ``(nv,)``.
        ft_cov: ``(S, 6, 6)`` reading noise covariances (covariance).
        normals: ``(K, 3)``, ``friction`` ``(K,)``, ``pushing`` ``(K,)`` (constrained graphs).
        extra: column name -> value, the extra columns chained corrections read.
        h_in: sensor -> ``(N, L, H)`` recurrent states of corrections inside the graph (``run``).
    """

    q: Any = None
    qd: Any = None
    qdd: Any = None
    ft: Any = None
    positions: Any = None
    active: Any = None
    directions: Any = None
    wrenches: Any = None
    ft_residual: Any = None
    omega: Any = None
    domega: Any = None
    proper_acc: Any = None
    tau_measured: Any = None
    tau_mask: Any = None
    ft_cov: Any = None
    normals: Any = None
    friction: Any = None
    pushing: Any = None
    extra: Mapping[str, Any] | None = None
    h_in: Mapping[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        """The given fields (None left out)."""
        return {
            f.name: v for f in dataclasses.fields(self) if (v := getattr(self, f.name)) is not None
        }


_FIELDS = frozenset(f.name for f in dataclasses.fields(Inputs))
#: Inputs a graph may not read (its layout has no slot of that kind), silently unused then.
_SLOT_DATA = frozenset(("directions", "wrenches", "extra"))
#: How :meth:`EstimatorRuntime.step` fills a field of the packed input.
_PLAIN, _FT, _MASK, _EXTRA, _STATE = range(5)


def _given(inputs: Any, args: tuple, named: Mapping[str, Any]) -> dict[str, Any]:
    """One dict of inputs (an :class:`Inputs`, a mapping, or old-style args), as given.

    Names are not checked here (:func:`_named` does, when a name is not a graph's); a dict is
    returned as it is (never modified).

    Raises:
        InputError: too many positional values.
    """
    if not args:
        if type(inputs) is dict and not named:
            return inputs  # the common case
        if isinstance(inputs, Inputs):
            return {**inputs.as_dict(), **named}
        if isinstance(inputs, Mapping):
            return {**inputs, **named}
    # q, qd, qdd, ft, positions, ... as earlier versions took them
    args = args if inputs is None else (inputs, *args)
    if len(args) > len(_POSITIONAL):
        raise InputError(f"at most {len(_POSITIONAL)} positional inputs {_POSITIONAL}")
    given = dict(zip(_POSITIONAL, args, strict=False))
    given.update(named)
    return given


def _named(given: Mapping[str, Any]) -> dict[str, Any]:
    """``given`` by the one name of each input, the None values left out.

    Raises:
        InputError: an unknown input name.
    """
    out = {}
    for k, v in given.items():
        c = fmt.canonical(k)
        if c not in _FIELDS:
            raise InputError(f"unknown input {k!r}; the inputs are {sorted(_FIELDS)}")
        if v is not None:
            out[c] = v
    return out


def session_options(intra_op_threads: int = 1) -> ort.SessionOptions:
    """Onnxruntime options for one frame per call (chosen by measurement, benchmarks/runtime.py).

    One intra-op thread and sequential execution (a single frame has no parallel work worth a
    thread hand-off; more threads measured slower), no spinning (a spinning pool competes with the
    caller on a loaded machine), every graph optimisation (constant folding, Gemm fusion), memory
    arena and pattern planning on (output buffers are reused between calls).
    """
    so = ort.SessionOptions()
    so.intra_op_num_threads = intra_op_threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so


def _metadata(session: ort.InferenceSession) -> dict[str, Any]:
    return fmt.decode(session.get_modelmeta().custom_metadata_map)


def identity_of(robot: Any) -> RobotIdentity:
    """The :class:`~torchcontact.identity.RobotIdentity` of a model, URDF path or ``"tcarm"``.

    A model carries its identity; for a URDF the model is built (this imports torch).

    Raises:
        ModelMismatchError: ``robot`` names no readable URDF file, or torch is not installed.
    """
    ident = getattr(robot, "identity", None)
    if isinstance(ident, RobotIdentity):
        return ident
    try:
        from torchcontact.model import RobotModel
    except ImportError:  # pragma: no cover - a deployment without torch
        raise ModelMismatchError(
            "the URDF's text differs from the one the graph was exported with; comparing the"
            " parsed robots needs torch (pip install torch) or a re-export"
        ) from None
    if str(robot) == "tcarm":
        from torchcontact.robots import tcarm_path

        robot = tcarm_path()
    return RobotModel.from_urdf(robot).identity


def robot_identity(robot: Any) -> tuple[str, tuple[str, ...] | None]:
    """URDF sha256 and joint names of ``robot``, without torch.

    Args:
        robot: a :class:`torchcontact.RobotModel` (or anything with ``urdf_sha256`` and
            ``joint_names``), a URDF file path, or ``"tcarm"`` (the bundled arm).

    Returns:
        ``(sha256 of the URDF text, joint names or None)``; for a file the hash identifies the
        text, and with it the joint order the exporter derived from it.

    Raises:
        ModelMismatchError: ``robot`` names no readable URDF file.
    """
    if hasattr(robot, "urdf_sha256"):
        return str(robot.urdf_sha256), tuple(getattr(robot, "joint_names", ())) or None
    if str(robot) == "tcarm":
        from torchcontact.robots import tcarm_path

        robot = tcarm_path()
    p = Path(os.fspath(robot))
    if not p.is_file():
        raise ModelMismatchError(f"robot {str(robot)!r}: no such URDF file (or 'tcarm')")
    return hashlib.sha256(p.read_text().encode()).hexdigest(), None


class ResidualGraph:
    """A residual-correction graph: what it reads, what it returns, and its recurrent state.

    Two interfaces are understood (``metadata_props["format"]``):

    * ``torchcontact.residual/1`` (``python -m export residual``): input ``features (N, F)``,
      columns named ``q.<joint>``, ``qd.<joint>``, ``qdd.<joint>`` or an extra column
      (``feature_names``), optional ``h_in (N, L, H)``; output ``residual (N, 6)`` (and
      ``h_out``);
    * ``torchcontact.residual-graph/1`` (correction stacks): inputs ``q, qd, qdd (N, nv)`` in
      ``joint_names`` order, optional ``extra (N, E)`` (``extra_columns``) and ``h_in``;
      output ``correction (N, 6)`` (and ``h_out``).

    Either output is a wrench ``[N; N m]`` in the sensor's frame and measure direction, subtracted
    from that sensor's reading. This class is the one place that knows these interfaces: the
    exporter wires them into a combined graph, the runtime feeds them.

    Attributes:
        path: the file.
        sensor: the sensor it corrects.
        joint_names: its joint order.
        extra: names of its extra input columns (e.g. ``temperature``).
        state_shape: ``(L, H)`` of a recurrent graph, else None.
        robot_sha256: URDF hash recorded at training ("" if none).
        inputs: per graph input, ``(name, columns)`` with columns ``("q" | "qd" | "qdd", joint)``
            or ``("extra", name)`` (None for ``h_in``).
        output: the correction's output name.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        metadata: Mapping[str, Any],
        input_names: Sequence[str],
        output_names: Sequence[str],
    ) -> None:
        self.path = str(path)
        fmt_ = metadata.get(Key.FORMAT)
        if fmt_ not in RESIDUAL_FORMATS:
            raise ModelMismatchError(
                f"{path} is not a residual-correction graph (format {fmt_!r}, expected one of"
                f" {list(RESIDUAL_FORMATS)})"
            )
        self.format = fmt_
        self.sensor = str(metadata.get(Key.SENSOR, ""))
        self.joint_names = tuple(metadata.get(Key.JOINT_NAMES, []))
        self.robot_sha256 = str(metadata.get(Key.ROBOT_SHA256, ""))
        self.identity = fmt.recorded_identity(metadata)
        recurrent = str(metadata.get(Key.RECURRENT, "false")).lower() == "true"
        shape = metadata.get(Key.STATE_SHAPE)
        self.state_shape = tuple(int(s) for s in shape[1:]) if recurrent and shape else None
        inputs: list[tuple[str, list | None]] = []
        if fmt_ == RESIDUAL_FORMAT:
            cols: list = []
            extra: list[str] = []
            for name in metadata.get(Key.FEATURE_NAMES, []):
                prefix, _, joint = name.partition(".")
                if prefix in ("q", "qd", "qdd") and joint in self.joint_names:
                    cols.append((prefix, joint))
                else:
                    cols.append(("extra", name))
                    extra.append(name)
            inputs.append((input_names[0], cols))
            self.output = output_names[0]
        else:
            extra = list(metadata.get(Key.EXTRA_COLUMNS, []))
            for name in input_names:
                if name in ("q", "qd", "qdd"):
                    inputs.append((name, [(name, j) for j in self.joint_names]))
                elif name == "extra":
                    inputs.append((name, [("extra", c) for c in extra]))
            self.output = "correction"
        if self.state_shape is not None:
            inputs.append(("h_in", None))
        self.extra = tuple(extra)
        self.inputs = inputs
        self.output_names = tuple(output_names)
        self.dtype = np.dtype(str(metadata.get(Key.DTYPE, "float32")))

    @classmethod
    def load(cls, path: str | os.PathLike, intra_op_threads: int = 1) -> ResidualGraph:
        """Open a correction graph (its session is kept in ``.session``).

        Raises:
            InputError: no such file.
            ModelMismatchError: the file is not a correction graph.
        """
        if not os.path.isfile(path):
            raise InputError(f"residual graph {path}: no such file")
        sess = ort.InferenceSession(
            str(path), session_options(intra_op_threads), providers=["CPUExecutionProvider"]
        )
        obj = cls(
            path,
            _metadata(sess),
            [i.name for i in sess.get_inputs()],
            [o.name for o in sess.get_outputs()],
        )
        obj.session = sess
        return obj

    def check(self, joint_names: Sequence[str], sensors: Sequence[str], robot: Any) -> None:
        """Refuse a correction made for another robot, joint set or sensor.

        Args:
            joint_names: the estimator's joints.
            sensors: the estimator's sensors.
            robot: the estimator's robot: a model (its identity and URDF text hash), or the
                metadata of an estimator graph (the identity and text hash it records).

        Raises:
            ModelMismatchError: naming what differs (the first differing quantity when both
                record an identity).
        """
        if isinstance(robot, Mapping):
            text, ident = str(robot.get(Key.URDF_SHA256, "")), fmt.recorded_identity(robot)
        else:
            text, ident = str(robot.urdf_sha256), robot.identity
        if self.identity is not None and ident is not None:  # compare the parsed robots
            why = self.identity.difference(ident)
            if why is not None:
                raise ModelMismatchError(
                    f"residual graph {self.path} was trained on a robot with sha256"
                    f" {self.identity.sha256[:12]}..., not this one ({why})"
                )
        elif self.robot_sha256 and self.robot_sha256 != text:  # earlier graphs: the URDF text
            raise ModelMismatchError(
                f"residual graph {self.path} was trained on a robot with URDF sha256"
                f" {self.robot_sha256[:12]}..., not this one ({text[:12]}...)"
            )
        missing = [j for j in self.joint_names if j not in joint_names]
        if missing:
            raise ModelMismatchError(
                f"residual graph {self.path} reads joints {missing} the estimator does not have"
            )
        if self.sensor not in sensors:
            raise ModelMismatchError(
                f"residual graph {self.path} corrects sensor {self.sensor!r}, not one of"
                f" {list(sensors)}"
            )

    def feed(
        self,
        joint_names: Sequence[str],
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        extra: Mapping[str, np.ndarray],
        state: np.ndarray | None,
    ) -> dict[str, np.ndarray]:
        """The graph's inputs for ``N`` frames given in the estimator's joint order.

        Args:
            joint_names: the order of ``q``, ``qd``, ``qdd`` (``(N, nv)``).
            q: ``(N, nv)`` positions; ``qd``, ``qdd`` likewise.
            qd: ``(N, nv)``.
            qdd: ``(N, nv)``.
            extra: column name -> ``(N,)`` values.
            state: ``(N, L, H)`` recurrent state (recurrent graphs).

        Raises:
            InputError: an extra column is missing.
        """
        missing = [c for c in self.extra if c not in extra]
        if missing:
            raise InputError(
                f"the residual correction of {self.sensor!r} needs extra input"
                f" {missing[0]!r} (got {sorted(extra)})"
            )
        n = q.shape[0]
        cols = [np.asarray(extra[c], dtype=np.float64).reshape(n, 1) for c in self.extra]
        src = np.concatenate([q, qd, qdd, *cols], axis=1)
        position = fmt.JointColumns(joint_names, self.extra)
        feed = {}
        for name, columns in self.inputs:
            if columns is None:
                feed[name] = state.astype(self.dtype, copy=False)
            else:
                feed[name] = src[:, [position(*c) for c in columns]].astype(self.dtype)
        return feed


class EstimatorRuntime:
    """An exported contact estimator, loaded for inference.

    Args:
        path: the batched graph ``<name>.onnx`` (or the single-frame ``<name>.step.onnx``) written
            by :func:`torchcontact.export.export_estimator`; the other one is found beside it.
        robot: the robot the caller runs (a URDF path, ``"tcarm"``, or a ``RobotModel``): the
            graph is refused unless it was exported for this URDF (sha256 of its text, and with a
            model its joint names).
        residual: a residual-correction graph (:class:`ResidualGraph`) to chain before the
            estimator, or a list of them (one per sensor); not with a graph that already holds
            its correction.
        expect_robot_sha256: refuse the graph unless its URDF hash matches.
        expect_joint_names: refuse the graph unless its joint order matches.
        expect_sensors: refuse the graph unless its F/T sensor names (in order) match.
        expect_slots: refuse the graph unless its ``(links, kinds)`` slot layout matches.
        intra_op_threads: onnxruntime threads (1: the lowest single-frame latency).
        step_graph: load the single-frame graph for :meth:`step` (False: :meth:`step` runs the
            batched graph with ``N = 1``).

    Attributes:
        metadata: the graph's ``metadata_props`` (JSON values decoded).
        nv, S, K: joints, sensors, contact slots.
        joint_names, sensor_names, slot_links, slot_kinds: the layout.
        dtype: numpy dtype of the graphs' inputs and outputs.
        extra: names of the extra input columns the chained corrections read.

    Raises:
        InputError: no such file.
        ModelMismatchError: the file is not an estimator graph of this format, or a check fails.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        robot: Any = None,
        *,
        residual: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
        expect_robot_sha256: str | None = None,
        expect_joint_names: Sequence[str] | None = None,
        expect_sensors: Sequence[str] | None = None,
        expect_slots: tuple[Sequence[str], Sequence[str]] | None = None,
        intra_op_threads: int = 1,
        step_graph: bool = True,
    ) -> None:
        path = Path(os.fspath(path))
        if not path.is_file():
            raise InputError(f"{path}: no such file")
        self._so = session_options(intra_op_threads)
        # open the small single-frame graph first when it lies beside the batched one: the
        # batched graph (thousands of nodes, seconds to optimise) loads on the first run()
        step_file = path.with_name(f"{path.name.removesuffix('.onnx')}.step.onnx")
        if step_graph and not path.name.endswith(".step.onnx") and step_file.is_file():
            first = ort.InferenceSession(
                str(step_file), self._so, providers=["CPUExecutionProvider"]
            )
            if _metadata(first).get(Key.BATCHED_GRAPH) != path.name:
                first = ort.InferenceSession(
                    str(path), self._so, providers=["CPUExecutionProvider"]
                )
        else:
            first = ort.InferenceSession(str(path), self._so, providers=["CPUExecutionProvider"])
        meta = _metadata(first)
        if meta.get(Key.FORMAT) != FORMAT:
            raise ModelMismatchError(
                f"{path} is not a torchcontact estimator graph of format {FORMAT!r} (found"
                f" {meta.get('format')!r}): re-export it with python -m export estimator"
            )
        self.metadata = meta
        self.path = str(path)
        graph = meta.get(Key.GRAPH)
        self._batched: ort.InferenceSession | None = first if graph == "batched" else None
        self._batched_path = path.parent / str(meta.get(Key.BATCHED_GRAPH))
        self.step_session: ort.InferenceSession | None = first if graph == "step" else None
        other = path.parent / str(meta.get(Key.STEP_GRAPH))
        if graph == "batched" and step_graph and meta.get(Key.STEP_GRAPH) and other.is_file():
            self.step_session = ort.InferenceSession(
                str(other), self._so, providers=["CPUExecutionProvider"]
            )
            smeta = _metadata(self.step_session)
            if {k: v for k, v in smeta.items() if k != "graph"} != {
                k: v for k, v in meta.items() if k != "graph"
            }:
                raise ModelMismatchError(
                    f"{other} is not the single-frame graph of {path} (re-export both)"
                )
        self.joint_names = tuple(meta[Key.JOINT_NAMES])
        self.sensor_names = tuple(s["name"] for s in meta[Key.SENSORS])
        self.slot_links, self.slot_kinds = tuple(meta[Key.SLOT_LINKS]), tuple(meta[Key.SLOT_KINDS])
        self.nv, self.S, self.K = (
            len(self.joint_names),
            len(self.sensor_names),
            len(self.slot_links),
        )
        self.dtype = np.dtype(meta[Key.DTYPE])
        self._check(robot, expect_robot_sha256, expect_joint_names, expect_sensors, expect_slots)
        # chained corrections: inside the graphs (export --residual) or run here
        self.residuals: list[ResidualGraph] = []
        inside = list(meta.get(Key.RESIDUALS, []))
        if residual is not None:
            if inside:
                raise ModelMismatchError(
                    f"{path} already holds residual corrections for {[r['sensor'] for r in inside]}"
                )
            paths = [residual] if isinstance(residual, (str, os.PathLike)) else list(residual)
            for p in paths:
                rg = ResidualGraph.load(p, intra_op_threads)
                rg.check(self.joint_names, self.sensor_names, meta)
                self.residuals.append(rg)
            extra = [c for rg in self.residuals for c in rg.extra]
        else:
            extra = [c for r in inside for c in r["extra"]]
        self.extra = tuple(dict.fromkeys(extra))
        self._inside = inside
        self._state: dict[str, np.ndarray] = {}
        self.reset()
        self._setup_step()

    # ------------------------------------------------------------------------------- checks

    def _check(self, robot, sha256, joints, sensors, slots) -> None:
        meta, path = self.metadata, self.path
        name = meta.get(Key.ROBOT)
        recorded = fmt.recorded_identity(meta)
        if robot is not None:
            h, names = robot_identity(robot)
            if h != meta[Key.URDF_SHA256]:
                # another text: the same robot when the parsed models agree (graphs that record
                # the robot's identity; earlier graphs compare the text only)
                why = f"URDF sha256 {h[:12]}..."
                if recorded is not None:
                    ident = identity_of(robot)
                    why = recorded.difference(ident)
                if why is not None:
                    raise ModelMismatchError(
                        f"{path} was exported for robot {name!r} (URDF sha256"
                        f" {meta[Key.URDF_SHA256][:12]}...), not for this robot ({why}):"
                        " re-export it for this robot"
                    )
            if names is not None and tuple(names) != self.joint_names:
                raise ModelMismatchError(
                    f"{path} expects joints {list(self.joint_names)} (robot {name!r}), the robot"
                    f" has {list(names)}"
                )
        accepted = {meta[Key.URDF_SHA256], meta.get(Key.ROBOT_IDENTITY_SHA256)}
        if sha256 is not None and sha256 not in accepted:
            raise ModelMismatchError(
                f"{path} was exported for robot {name!r} with URDF sha256 {meta['urdf_sha256']},"
                f" not {sha256}: re-export it for this robot"
            )
        if joints is not None and tuple(joints) != self.joint_names:
            raise ModelMismatchError(
                f"{path} expects joints {list(self.joint_names)} (robot {name!r}), got"
                f" {list(joints)}"
            )
        if sensors is not None and tuple(sensors) != self.sensor_names:
            raise ModelMismatchError(
                f"{path} expects sensors {list(self.sensor_names)}, got {list(sensors)}"
            )
        if slots is not None and (tuple(slots[0]), tuple(slots[1])) != (
            self.slot_links,
            self.slot_kinds,
        ):
            have = list(zip(self.slot_links, self.slot_kinds, strict=True))
            raise ModelMismatchError(
                f"{path} has contact slots {have}, got {list(zip(slots[0], slots[1], strict=True))}"
            )

    def __repr__(self) -> str:
        return (
            f"EstimatorRuntime({self.path!r}, robot={self.metadata['robot']!r}, nv={self.nv},"
            f" sensors={list(self.sensor_names)}, slots={list(self.slot_kinds)},"
            f" dtype={self.dtype})"
        )

    def reset(self) -> None:
        """Zero the recurrent state of the chained corrections (a new time series starts)."""
        self._state = {}
        for rg in self.residuals:
            if rg.state_shape is not None:
                self._state[rg.path] = np.zeros((1, *rg.state_shape), rg.dtype)
        for r in self._inside:
            if r.get("state_shape"):
                self._state[r["sensor"]] = np.zeros(tuple(r["state_shape"]), self.dtype)

    # ---------------------------------------------------------------------------- single frame

    def _setup_step(self) -> None:
        if self.step_session is None:
            self._x = None
            return
        lay = {
            k: (int(o), tuple(int(s) for s in sh))
            for k, (o, sh) in self.metadata[Key.STEP_INPUTS].items()
        }
        out = {
            k: (int(o), tuple(int(s) for s in sh))
            for k, (o, sh) in self.metadata[Key.STEP_OUTPUTS].items()
        }
        size = max(o + int(np.prod(sh)) for o, sh in lay.values())
        self._x = np.zeros((1, size), self.dtype)
        self._xv = {
            k: self._x[0, o : o + int(np.prod(sh))].reshape(sh) for k, (o, sh) in lay.items()
        }
        self._lay = lay
        self._out = {k: (o, o + int(np.prod(sh)), sh) for k, (o, sh) in out.items()}
        self._fresh: set[str] = set()
        # per field of the packed input: how step() fills it, and its default (None: required;
        # ones for the activity flags; zeros for the rest)
        defaults = {k: None for k in fmt.REQUIRED} | {k: 1.0 for k in fmt.ONES}
        special = {"ft": _FT, "tau_mask": _MASK, fmt.EXTRA: _EXTRA}
        self._fill = [
            (
                k,
                v,
                _STATE if k.startswith("h_in.") else special.get(k, _PLAIN),
                defaults.get(k, 0.0),
            )
            for k, v in self._xv.items()
        ]
        self._accepts = frozenset(self._xv) | _SLOT_DATA
        self._in_name = self.step_session.get_inputs()[0].name
        # the binding's own run (skips the Python wrapper's per-call checks)
        self._run = self.step_session._sess.run
        self._out_names = [o.name for o in self.step_session.get_outputs()]
        self._ro = ort.RunOptions()

    def _put(self, name: str, view: np.ndarray, value: Any, default: float | None) -> None:
        """Write one input field of the packed vector (``default`` when ``value`` is None)."""
        if value is None:
            if default is None:
                raise InputError(f"{name} is required by this graph, shape {view.shape}")
            if name not in self._fresh:
                view[...] = default
                self._fresh.add(name)
            return
        self._fresh.discard(name)
        if type(value) is np.ndarray and value.shape == view.shape:
            view[...] = value
            return
        arr = np.asarray(value)
        if arr.shape != view.shape:
            if (
                arr.size == view.size
                and arr.ndim <= 1 + view.ndim
                and arr.squeeze().shape == view.squeeze().shape
            ):
                arr = arr.reshape(view.shape)
            else:
                raise InputError(f"{name} must have shape {view.shape}, got {arr.shape}")
        view[...] = arr

    def step(self, inputs: Inputs | Mapping[str, Any] | None = None, /, *args: Any,
             **named: Any) -> dict[str, Any]:  # fmt: skip
        """Estimate one frame from the raw readings.

        Args:
            inputs: an :class:`Inputs` or a mapping name -> value (one frame's shapes, see
                :class:`Inputs`; the older spellings of :data:`~torchcontact.onnx.format.INPUTS`
                are accepted). Earlier versions' form ``step(q, qd, qdd, ft, positions, active,
                directions, wrenches, ft_residual, **keywords)`` is accepted too.
            *args: the positional values of that earlier form.
            **named: inputs by name (added to ``inputs``).

        Returns:
            ``force``, ``moment`` ``(K, 3)`` (N, N m; link frames, moment about the point),
            ``joint_torques (nv,)``, ``rank``, ``unknowns`` ``(S,)`` int64, ``residual (S,)``,
            ``status`` (int, 0 ok; bits of :class:`torchcontact.Status`), ``covariance
            (K, 6, 6)`` when exported with it, and a constrained graph's ``converged``,
            ``iterations`` ``(S,)`` and ``cone_active (K,)``.

        Raises:
            InputError: a wrong shape, an unknown input, a missing required input or extra
                column.
        """
        given = _given(inputs, args, named)
        if self.step_session is None or not given.keys() <= self._accepts:
            given = _named(given)  # old spellings, None for absent
        if self.step_session is None:  # the batched graph with N = 1
            one = {k: (np.asarray(v)[None] if k not in ("extra", "h_in") else v)
                   for k, v in given.items()}  # fmt: skip
            if "ft" in given:
                one["ft"] = np.asarray(self._ft_array(given["ft"]), np.float64).reshape(
                    1, self.S, 6
                )
            if "extra" in given:
                one["extra"] = {k: np.atleast_1d(v) for k, v in given["extra"].items()}
            out = self.run(one)
            return {k: (v[0] if k != "status" else int(v[0])) for k, v in out.items()}
        if "ft" not in given:
            raise InputError(f"ft is required by this graph, shape {self._xv['ft'].shape}")
        ft = self._ft_array(given["ft"])
        extra = given.get("extra")
        if self.residuals:
            ft = ft - self._correct(given.get("q"), given.get("qd"), given.get("qdd"), extra,
                                    batch=False)  # fmt: skip
        if not given.keys() <= self._accepts:
            # a layout without force_dir (known) slots does not read directions (wrenches)
            bad = sorted(given.keys() - self._accepts)
            raise InputError(f"this graph has no input {bad[0]!r} (exported without it)")
        put = self._put
        for name, view, kind, default in self._fill:  # the packed input's fields, in order
            if kind == _PLAIN:
                put(name, view, given.get(name), default)
            elif kind == _FT:
                put(name, view, ft, None)
            elif kind == _MASK:
                value = given.get(name)
                if value is None and given.get("tau_measured") is not None:
                    value = np.isfinite(np.asarray(given["tau_measured"], dtype=float))
                put(name, view, value, default)
            elif kind == _EXTRA:
                vals = extra or {}
                missing = [c for c in self.extra if c not in vals]
                if missing:
                    raise InputError(f"extra inputs {missing} are required by the corrections")
                view[...] = [vals[c] for c in self.extra]
            else:  # a recurrent correction's state, carried from the previous step
                view[...] = self._state[name[5:]]
        out = self._run(self._out_names, {self._in_name: self._x}, self._ro)[0][0]
        lo = self._out
        a, b, sh = lo["fm"]
        fm = out[a:b].reshape(sh)
        a, b, _ = lo["joint_torques"]
        res = {"force": fm[:, 0:3], "moment": fm[:, 3:6], "joint_torques": out[a:b]}
        a, b, _ = lo["rank"]
        res["rank"] = out[a:b].astype(np.int64)
        a, b, _ = lo["unknowns"]
        res["unknowns"] = out[a:b].astype(np.int64)
        a, b, _ = lo["residual"]
        res["residual"] = out[a:b]
        res["status"] = int(out[lo["status"][0]])
        if "covariance" in lo:
            res["covariance"] = self._view(out, "covariance")
        for r in self._inside:
            if r.get("state_shape"):
                self._state[r["sensor"]] = self._view(out, fmt.state_out(r["sensor"])).copy()
        return res

    def _view(self, out: np.ndarray, name: str) -> np.ndarray:
        a, b, sh = self._out[name]
        return out[a:b].reshape(sh)

    def _ft_array(self, ft: Any) -> np.ndarray:
        if isinstance(ft, Mapping):
            missing = [s for s in self.sensor_names if s not in ft]
            if missing:
                raise InputError(f"ft is missing readings of sensors {missing}")
            return np.stack(
                [np.asarray(ft[s], dtype=np.float64).reshape(6) for s in self.sensor_names]
            )
        return np.asarray(ft)

    def _correct(self, q, qd, qdd, extra, batch: bool) -> np.ndarray:
        """Corrections of the separately chained residual graphs, ``(S, 6)`` or ``(N, S, 6)``."""
        q2 = np.atleast_2d(np.asarray(q, dtype=np.float64))
        n = q2.shape[0]
        qd2 = np.asarray(qd, dtype=np.float64).reshape(n, -1)
        qdd2 = np.asarray(qdd, dtype=np.float64).reshape(n, -1)
        ex = {k: np.asarray(v, dtype=np.float64).reshape(n) for k, v in (extra or {}).items()}
        corr = np.zeros((n, self.S, 6))
        for rg in self.residuals:
            state = None
            if rg.state_shape is not None:
                state = self._state[rg.path]
                if state.shape[0] != n:
                    state = np.zeros((n, *rg.state_shape), rg.dtype)
            outs = rg.session.run(None, rg.feed(self.joint_names, q2, qd2, qdd2, ex, state))
            corr[:, self.sensor_names.index(rg.sensor)] += outs[0]
            if rg.state_shape is not None and not batch:
                self._state[rg.path] = outs[1]
        return corr if batch else corr[0]

    # ----------------------------------------------------------------------------------- batch

    def _batched_session(self) -> ort.InferenceSession:
        if self._batched is None:
            if not self._batched_path.is_file():
                raise ModelMismatchError(f"the batched graph {self._batched_path} is missing")
            self._batched = ort.InferenceSession(
                str(self._batched_path), self._so, providers=["CPUExecutionProvider"]
            )
        return self._batched

    def run(self, inputs: Inputs | Mapping[str, Any] | None = None, /, *args: Any,
            chunk_size: int = 16384, **named: Any) -> dict[str, np.ndarray]:  # fmt: skip
        """Estimate ``N`` independent frames with the batched graph.

        Args:
            inputs: an :class:`Inputs` or a mapping name -> value, each with a leading ``N``
                (``ft`` ``(N, S, 6)``, ``extra`` column -> ``(N,)``, ``h_in`` sensor ->
                ``(N, L, H)`` recurrent states of corrections inside the graph, default zeros,
                each row an independent frame). The earlier form ``run(q, qd, qdd, ft, ...)``
                is accepted too.
            *args: the positional values of that earlier form.
            chunk_size: frames per graph call (bounds memory, keeps the working set in cache).
            **named: inputs by name (added to ``inputs``).

        Returns:
            As :meth:`step` with a leading ``N``; ``status`` ``(N,)`` int64.

        Raises:
            InputError: a wrong shape, an unknown input or a missing required input.
        """
        given = _given(inputs, args, named)
        sess = self._batched_session()
        if "q" not in given:
            raise InputError("q is required by this graph, shape (N, nv)")
        n = int(np.shape(given["q"])[0])
        extra, h_in = given.pop("extra", None), given.pop("h_in", None)
        if self.residuals and "ft" in given:
            corr = self._correct(given.get("q"), given.get("qd"), given.get("qdd"), extra, True)
            given["ft"] = np.asarray(given["ft"], dtype=np.float64) - corr
        inputs_ = {i.name for i in sess.get_inputs()}
        unknown = [k for k in given if k not in inputs_]
        if unknown:
            raise InputError(f"this graph has no inputs {unknown} (exported without them)")
        if "tau_measured" in given and "tau_mask" not in given:
            given["tau_mask"] = np.isfinite(np.asarray(given["tau_measured"], dtype=float))
        feed = {}
        for i in sess.get_inputs():
            trailing = tuple(int(d) for d in i.shape[1:])
            name = i.name
            if name == fmt.EXTRA:
                vals = extra or {}
                missing = [c for c in self.extra if c not in vals]
                if missing:
                    raise InputError(f"extra inputs {missing} are required by the corrections")
                x = (
                    np.stack([np.asarray(vals[c], dtype=float).reshape(n) for c in self.extra], -1)
                    if self.extra
                    else np.zeros((n, 0))
                )
            elif name.startswith("h_in."):
                x = (h_in or {}).get(name[5:])
                if x is None:
                    x = np.zeros((n, *trailing))
            else:
                x = given.get(name)
                if x is None:
                    if name in fmt.REQUIRED:
                        raise InputError(
                            f"{name} is required by this graph, shape (N, "
                            f"{', '.join(map(str, trailing))})"
                        )
                    x = (np.ones if name in fmt.ONES else np.zeros)((n, *trailing))
            x = np.asarray(x, dtype=self.dtype)
            if x.shape != (n, *trailing):
                raise InputError(
                    f"{name} must have shape ({n}, {', '.join(map(str, trailing))}), got {x.shape}"
                )
            feed[name] = x
        names = [o.name for o in sess.get_outputs()]
        parts = [
            sess.run(None, {k: v[s : s + chunk_size] for k, v in feed.items()})
            for s in range(0, max(n, 1), chunk_size)
        ]
        return {
            k: np.concatenate([p[i] for p in parts]) if len(parts) > 1 else parts[0][i]
            for i, k in enumerate(names)
        }
