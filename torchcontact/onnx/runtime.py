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

Example:
    >>> rt = EstimatorRuntime("tcarm.onnx", robot="tcarm")  # doctest: +SKIP
    >>> out = rt.step(q, qd, qdd, ft, positions, active)  # doctest: +SKIP
    >>> out["force"].shape  # (K, 3), N, in each slot's link frame  # doctest: +SKIP
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from torchcontact.errors import InputError, ModelMismatchError

__all__ = ["EstimatorRuntime", "ModelMismatchError", "ResidualGraph", "session_options"]

#: Format of the estimator graphs this runtime reads (``metadata_props["format"]``).
FORMAT = "torchcontact.estimator/2"
#: Formats of residual-correction graphs (:class:`ResidualGraph`).
RESIDUAL_FORMATS = ("torchcontact.residual/1", "torchcontact.residual-graph/1")


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
    meta: dict[str, Any] = {}
    for k, v in session.get_modelmeta().custom_metadata_map.items():
        try:
            meta[k] = json.loads(v)
        except (ValueError, TypeError):
            meta[k] = v
    return meta


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
        fmt = metadata.get("format")
        if fmt not in RESIDUAL_FORMATS:
            raise ModelMismatchError(
                f"{path} is not a residual-correction graph (format {fmt!r}, expected one of"
                f" {list(RESIDUAL_FORMATS)})"
            )
        self.format = fmt
        self.sensor = str(metadata.get("sensor", ""))
        self.joint_names = tuple(metadata.get("joint_names", []))
        self.robot_sha256 = str(metadata.get("robot_sha256", ""))
        recurrent = str(metadata.get("recurrent", "false")).lower() == "true"
        shape = metadata.get("state_shape")
        self.state_shape = tuple(int(s) for s in shape[1:]) if recurrent and shape else None
        inputs: list[tuple[str, list | None]] = []
        if fmt == "torchcontact.residual/1":
            cols: list = []
            extra: list[str] = []
            for name in metadata.get("feature_names", []):
                prefix, _, joint = name.partition(".")
                if prefix in ("q", "qd", "qdd") and joint in self.joint_names:
                    cols.append((prefix, joint))
                else:
                    cols.append(("extra", name))
                    extra.append(name)
            inputs.append((input_names[0], cols))
            self.output = output_names[0]
        else:
            extra = list(metadata.get("extra_columns", []))
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
        self.dtype = np.dtype(str(metadata.get("dtype", "float32")))

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

    def check(self, joint_names: Sequence[str], sensors: Sequence[str], urdf_sha256: str) -> None:
        """Refuse a correction made for another robot, joint set or sensor.

        Raises:
            ModelMismatchError: naming what differs.
        """
        if self.robot_sha256 and self.robot_sha256 != urdf_sha256:
            raise ModelMismatchError(
                f"residual graph {self.path} was trained on a robot with URDF sha256"
                f" {self.robot_sha256}, not {urdf_sha256}"
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
        src = {"q": q, "qd": qd, "qdd": qdd}
        pos = {j: i for i, j in enumerate(joint_names)}
        feed = {}
        for name, cols in self.inputs:
            if cols is None:
                feed[name] = state.astype(self.dtype, copy=False)
                continue
            out = []
            for kind, key in cols:
                if kind == "extra":
                    if key not in extra:
                        raise InputError(
                            f"the residual correction of {self.sensor!r} needs extra input"
                            f" {key!r} (got {sorted(extra)})"
                        )
                    out.append(np.asarray(extra[key], dtype=np.float64).reshape(-1))
                else:
                    out.append(src[kind][:, pos[key]])
            feed[name] = np.stack(out, -1).astype(self.dtype)
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
            if _metadata(first).get("batched_graph") != path.name:
                first = ort.InferenceSession(
                    str(path), self._so, providers=["CPUExecutionProvider"]
                )
        else:
            first = ort.InferenceSession(str(path), self._so, providers=["CPUExecutionProvider"])
        meta = _metadata(first)
        if meta.get("format") != FORMAT:
            raise ModelMismatchError(
                f"{path} is not a torchcontact estimator graph of format {FORMAT!r} (found"
                f" {meta.get('format')!r}): re-export it with python -m export estimator"
            )
        self.metadata = meta
        self.path = str(path)
        graph = meta.get("graph")
        self._batched: ort.InferenceSession | None = first if graph == "batched" else None
        self._batched_path = path.parent / str(meta.get("batched_graph"))
        self.step_session: ort.InferenceSession | None = first if graph == "step" else None
        other = path.parent / str(meta.get("step_graph"))
        if graph == "batched" and step_graph and meta.get("step_graph") and other.is_file():
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
        self.joint_names = tuple(meta["joint_names"])
        self.sensor_names = tuple(s["name"] for s in meta["sensors"])
        self.slot_links, self.slot_kinds = tuple(meta["slot_links"]), tuple(meta["slot_kinds"])
        self.nv, self.S, self.K = (
            len(self.joint_names),
            len(self.sensor_names),
            len(self.slot_links),
        )
        self.dtype = np.dtype(meta["dtype"])
        self._check(robot, expect_robot_sha256, expect_joint_names, expect_sensors, expect_slots)
        # chained corrections: inside the graphs (export --residual) or run here
        self.residuals: list[ResidualGraph] = []
        inside = list(meta.get("residuals", []))
        if residual is not None:
            if inside:
                raise ModelMismatchError(
                    f"{path} already holds residual corrections for {[r['sensor'] for r in inside]}"
                )
            paths = [residual] if isinstance(residual, (str, os.PathLike)) else list(residual)
            for p in paths:
                rg = ResidualGraph.load(p, intra_op_threads)
                rg.check(self.joint_names, self.sensor_names, meta["urdf_sha256"])
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
        name = meta.get("robot")
        if robot is not None:
            h, names = robot_identity(robot)
            if h != meta["urdf_sha256"]:
                raise ModelMismatchError(
                    f"{path} was exported for robot {name!r} (URDF sha256"
                    f" {meta['urdf_sha256'][:12]}...), not for this robot (sha256 {h[:12]}...):"
                    " re-export it for this robot"
                )
            if names is not None and tuple(names) != self.joint_names:
                raise ModelMismatchError(
                    f"{path} expects joints {list(self.joint_names)} (robot {name!r}), the robot"
                    f" has {list(names)}"
                )
        if sha256 is not None and meta["urdf_sha256"] != sha256:
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
            for k, (o, sh) in self.metadata["step_inputs"].items()
        }
        out = {
            k: (int(o), tuple(int(s) for s in sh))
            for k, (o, sh) in self.metadata["step_outputs"].items()
        }
        size = max(o + int(np.prod(sh)) for o, sh in lay.values())
        self._x = np.zeros((1, size), self.dtype)
        self._xv = {
            k: self._x[0, o : o + int(np.prod(sh))].reshape(sh) for k, (o, sh) in lay.items()
        }
        self._lay = lay
        self._out = {k: (o, o + int(np.prod(sh)), sh) for k, (o, sh) in out.items()}
        self._fresh: set[str] = set()
        self._in_name = self.step_session.get_inputs()[0].name
        # the binding's own run (skips the Python wrapper's per-call checks)
        self._run = self.step_session._sess.run
        self._out_names = [o.name for o in self.step_session.get_outputs()]
        self._ro = ort.RunOptions()

    def _put(self, name: str, value: Any, default: float | None = 0.0) -> None:
        """Write one input field of the packed vector (``default`` when ``value`` is None)."""
        view = self._xv.get(name)
        if view is None:
            if value is not None:
                raise InputError(f"this graph has no input {name!r} (exported without it)")
            return
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

    def step(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        ft: np.ndarray | Mapping[str, np.ndarray],
        positions: np.ndarray | None = None,
        active: np.ndarray | None = None,
        directions: np.ndarray | None = None,
        wrenches: np.ndarray | None = None,
        ft_residual: np.ndarray | None = None,
        *,
        omega: np.ndarray | None = None,
        domega: np.ndarray | None = None,
        proper_acc: np.ndarray | None = None,
        tau_measured: np.ndarray | None = None,
        tau_mask: np.ndarray | None = None,
        ft_cov: np.ndarray | None = None,
        extra: Mapping[str, float] | None = None,
        normals: np.ndarray | None = None,
        friction: np.ndarray | None = None,
        pushing: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """Estimate one frame from the raw readings.

        Args:
            q: ``(nv,)`` joint positions in :attr:`joint_names` order, rad or m.
            qd: ``(nv,)`` joint velocities.
            qdd: ``(nv,)`` joint accelerations.
            ft: ``(S, 6)`` readings ``[N; N m]`` (sensor frames and directions, raw: the chained
                corrections are subtracted inside), or sensor name -> ``(6,)``.
            positions: ``(K, 3)`` contact points in the slots' link frames, m (default zeros).
            active: ``(K,)`` 1/0 (or bool) slot activity (default all active).
            directions: ``(K, 3)`` force directions of ``force_dir`` slots (default zeros).
            wrenches: ``(K, 6)`` wrenches of ``known`` slots (default zeros).
            ft_residual: ``(S, 6)`` a further correction subtracted from ``ft`` (default zeros).
            omega: ``(3,)`` base angular velocity, rad/s (graphs exported with a moving base).
            domega: ``(3,)`` base angular acceleration, rad/s^2 (moving base).
            proper_acc: ``(3,)`` base proper acceleration, m/s^2 (moving base).
            tau_measured: ``(nv,)`` measured joint torques (graphs with torque rows).
            tau_mask: ``(nv,)`` which torques are measured (default: the finite ones).
            ft_cov: ``(S, 6, 6)`` reading noise covariances (graphs with the covariance).
            extra: the extra columns the corrections read, name -> value (e.g. temperature).
            normals: ``(K, 3)`` outward surface normals, link frames (constrained graphs,
                ``export_estimator(..., constraints=...)``; required there).
            friction: ``(K,)`` friction coefficients (constrained graphs; required there).
            pushing: ``(K,)`` 1/0: the contact can only push (constrained graphs; default 1).

        Returns:
            ``force``, ``moment`` ``(K, 3)`` (N, N m; link frames, moment about the point),
            ``joint_torques (nv,)``, ``rank``, ``unknowns`` ``(S,)`` int64, ``residual (S,)``,
            ``status`` (int, 0 ok; bits of ``torchcontact.STATUS``), ``covariance
            (K, 6, 6)`` when exported with it, and a constrained graph's ``converged``,
            ``iterations`` ``(S,)`` and ``cone_active (K,)``.

        Raises:
            InputError: a wrong shape, a missing required input or extra column.
        """
        if self.step_session is None:  # the batched graph with N = 1
            ft = np.asarray(self._ft_array(ft), dtype=np.float64).reshape(self.S, 6)
            out = self.run(
                *(
                    np.asarray(a)[None] if a is not None else None
                    for a in (q, qd, qdd, ft, positions, active, directions, wrenches, ft_residual)
                ),
                **{
                    k: (np.asarray(v)[None] if v is not None else None)
                    for k, v in dict(
                        omega=omega,
                        domega=domega,
                        proper_acc=proper_acc,
                        tau_measured=tau_measured,
                        tau_mask=tau_mask,
                        ft_cov=ft_cov,
                        normals=normals,
                        friction=friction,
                        pushing=pushing,
                    ).items()
                },
                extra={k: np.atleast_1d(v) for k, v in (extra or {}).items()},
            )
            return {k: (v[0] if k != "status" else int(v[0])) for k, v in out.items()}
        ft = self._ft_array(ft)
        if self.residuals:
            ft = ft - self._correct(q, qd, qdd, extra, batch=False)
        put = self._put
        put("q", q, None)
        put("qd", qd, None)
        put("qdd", qdd, None)
        put("ft", ft, None)
        put("positions", positions)
        put("active", active, 1.0)
        if "directions" in self._xv:  # (a layout without such slots does not read them)
            put("directions", directions)
        if "wrenches" in self._xv:
            put("wrenches", wrenches)
        put("ft_residual", ft_residual)
        for name, value in (("normals", normals), ("friction", friction), ("pushing", pushing)):
            put(name, value)  # only a constrained graph has them (it has no step graph)
        if "omega" in self._xv or omega is not None:
            put("omega", omega, None)
            put("domega", domega, None)
            put("proper_acc", proper_acc, None)
        if "tau_measured" in self._xv or tau_measured is not None:
            put("tau_measured", tau_measured, None)
            if tau_mask is None:
                tau_mask = np.isfinite(np.asarray(tau_measured, dtype=float))
            put("tau_mask", tau_mask, None)
        if "ft_cov" in self._xv or ft_cov is not None:
            put("ft_cov", ft_cov, None)
        if "extra" in self._xv:
            vals = extra or {}
            missing = [c for c in self.extra if c not in vals]
            if missing:
                raise InputError(f"extra inputs {missing} are required by the corrections")
            self._xv["extra"][...] = [vals[c] for c in self.extra]
        for r in self._inside:
            if r.get("state_shape"):
                self._xv[f"h_in.{r['sensor']}"][...] = self._state[r["sensor"]]
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
                self._state[r["sensor"]] = self._view(out, f"h_out.{r['sensor']}").copy()
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

    def run(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        ft: np.ndarray,
        positions: np.ndarray | None = None,
        active: np.ndarray | None = None,
        directions: np.ndarray | None = None,
        wrenches: np.ndarray | None = None,
        ft_residual: np.ndarray | None = None,
        *,
        omega: np.ndarray | None = None,
        domega: np.ndarray | None = None,
        proper_acc: np.ndarray | None = None,
        tau_measured: np.ndarray | None = None,
        tau_mask: np.ndarray | None = None,
        ft_cov: np.ndarray | None = None,
        extra: Mapping[str, np.ndarray] | None = None,
        h_in: Mapping[str, np.ndarray] | None = None,
        chunk_size: int = 16384,
        normals: np.ndarray | None = None,
        friction: np.ndarray | None = None,
        pushing: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Estimate ``N`` independent frames with the batched graph.

        Args:
            q: ``(N, nv)``; the other arguments as in :meth:`step` with a leading ``N``.
            qd: ``(N, nv)``.
            qdd: ``(N, nv)``.
            ft: ``(N, S, 6)`` raw readings.
            positions: ``(N, K, 3)``.
            active: ``(N, K)``.
            directions: ``(N, K, 3)``.
            wrenches: ``(N, K, 6)``.
            ft_residual: ``(N, S, 6)``.
            omega: ``(N, 3)`` (moving base).
            domega: ``(N, 3)``.
            proper_acc: ``(N, 3)``.
            tau_measured: ``(N, nv)`` (torque rows).
            tau_mask: ``(N, nv)``.
            ft_cov: ``(N, S, 6, 6)`` (covariance).
            extra: column -> ``(N,)`` for the corrections.
            h_in: sensor -> ``(N, L, H)`` recurrent states of corrections inside the graph
                (default zeros; each row is an independent frame).
            chunk_size: frames per graph call (bounds memory, keeps the working set in cache).
            normals: ``(N, K, 3)`` (constrained graphs).
            friction: ``(N, K)`` (constrained graphs).
            pushing: ``(N, K)`` (constrained graphs; default ones).

        Returns:
            As :meth:`step` with a leading ``N``; ``status`` ``(N,)`` int64.

        Raises:
            InputError: a wrong shape or a missing required input.
        """
        sess = self._batched_session()
        n = int(np.shape(q)[0])
        if self.residuals:
            ft = np.asarray(ft, dtype=np.float64) - self._correct(q, qd, qdd, extra, batch=True)
        given = dict(
            q=q,
            qd=qd,
            qdd=qdd,
            ft=ft,
            positions=positions,
            active=active,
            directions=directions,
            wrenches=wrenches,
            ft_residual=ft_residual,
            omega=omega,
            domega=domega,
            proper_acc=proper_acc,
            tau_measured=tau_measured,
            tau_mask=tau_mask,
            ft_cov=ft_cov,
            normals=normals,
            friction=friction,
            pushing=pushing,
        )
        inputs = {i.name for i in sess.get_inputs()}
        optional = ("omega", "domega", "proper_acc", "tau_measured", "tau_mask", "ft_cov")
        optional += ("normals", "friction", "pushing")
        unknown = [k for k in optional if given[k] is not None and k not in inputs]
        if unknown:
            raise InputError(f"this graph has no inputs {unknown} (exported without them)")
        if tau_measured is not None and tau_mask is None:
            given["tau_mask"] = np.isfinite(np.asarray(tau_measured, dtype=float))
        feed = {}
        for i in sess.get_inputs():
            trailing = tuple(int(d) for d in i.shape[1:])
            name = i.name
            if name == "extra":
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
                    if name in (
                        "q",
                        "qd",
                        "qdd",
                        "ft",
                        "omega",
                        "domega",
                        "proper_acc",
                        "tau_measured",
                        "ft_cov",
                        "normals",
                        "friction",
                    ):
                        raise InputError(
                            f"{name} is required by this graph, shape (N, "
                            f"{', '.join(map(str, trailing))})"
                        )
                    ones = name in ("active", "pushing")
                    x = np.ones((n, *trailing)) if ones else np.zeros((n, *trailing))
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
