"""Residual-correction graphs as the runtime runs them beside an estimator (onnxruntime, numpy).

:class:`ResidualGraph` is the one place that knows the correction graphs' interfaces: the
exporter wires them into combined graphs (:mod:`torchcontact.onnx.batched`), the runtime feeds
them (:class:`~torchcontact.onnx.runtime.EstimatorRuntime`, ``residual=``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from torchcontact.errors import InputError, ModelMismatchError
from torchcontact.onnx import format as fmt
from torchcontact.onnx.backends import metadata_of, open_session, session_options
from torchcontact.onnx.format import RESIDUAL_FORMAT, RESIDUAL_FORMATS, Key

__all__ = ["ResidualGraph"]


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
        sess = open_session(path, session_options(intra_op_threads))
        obj = cls(
            path,
            metadata_of(sess),
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
