"""Run an exported estimator graph with onnxruntime and numpy only (no torch import).

The graph and its ``metadata_props`` come from :func:`torchcontact.export.export_estimator`
(``python -m export estimator ...``). Session options favour single-frame latency: one intra-op
thread, no spinning, full graph optimisation, CPU execution provider. When the export wrote the
single-frame graph (``<stem>.step.onnx``, static shapes ``N = 1``) beside the file,
:meth:`EstimatorRuntime.step` runs that one: with its shape arithmetic folded away it has fewer
nodes and a lower latency; :meth:`EstimatorRuntime.run` keeps the dynamic-batch graph.

Example:
    >>> rt = EstimatorRuntime("tcarm.onnx", expect_joint_names=joint_names)  # doctest: +SKIP
    >>> out = rt.step(q, qd, qdd, ft, positions, active)  # doctest: +SKIP
    >>> out["force"].shape  # (K, 3), N, in each slot's link frame  # doctest: +SKIP
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence

import numpy as np
import onnxruntime as ort

from torchcontact.errors import ModelMismatchError  # noqa: F401  (re-exported)

__all__ = ["EstimatorRuntime", "ModelMismatchError"]

_FORMAT = "torchcontact.estimator/1"
_INPUTS = ("q", "qd", "qdd", "ft", "positions", "directions", "wrenches", "active", "ft_residual")
#: More inputs of a friction-cone constrained graph (metadata ``constraints``).
_CONE_INPUTS = ("normals", "friction", "pushing")


class EstimatorRuntime:
    """An exported contact estimator, loaded for inference.

    Args:
        path: ``.onnx`` file written by :func:`torchcontact.export.export_estimator`.
        expect_robot_sha256: refuse the file unless its URDF hash matches.
        expect_joint_names: refuse the file unless its joint order matches.
        expect_sensors: refuse the file unless its F/T sensor names (in order) match.
        expect_slots: refuse the file unless its ``(links, kinds)`` slot layout matches.
        intra_op_threads: onnxruntime intra-op threads (1: best single-frame latency).
        step_graph: load the single-frame graph named in the metadata for :meth:`step` when it
            lies beside ``path`` (False: :meth:`step` runs the dynamic graph).

    Attributes:
        metadata: the file's ``metadata_props`` (JSON values decoded).
        nv, S, K: joints, sensors, contact slots.
        dtype: numpy dtype of the graph's inputs and outputs.

    Raises:
        ModelMismatchError: the file is not an estimator graph or an expectation fails.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        expect_robot_sha256: str | None = None,
        expect_joint_names: Sequence[str] | None = None,
        expect_sensors: Sequence[str] | None = None,
        expect_slots: tuple[Sequence[str], Sequence[str]] | None = None,
        intra_op_threads: int = 1,
        step_graph: bool = True,
    ) -> None:
        so = ort.SessionOptions()
        so.intra_op_num_threads = intra_op_threads
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        so.add_session_config_entry("session.inter_op.allow_spinning", "0")
        self.session = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        raw = self.session.get_modelmeta().custom_metadata_map
        if raw.get("format") != _FORMAT:
            raise ModelMismatchError(
                f"{path} is not a torchcontact estimator graph (format {raw.get('format')!r},"
                f" expected {_FORMAT!r})"
            )
        meta: dict = {}
        for k, v in raw.items():
            try:
                meta[k] = json.loads(v)
            except (ValueError, TypeError):
                meta[k] = v
        self.metadata = meta
        self.path = str(path)
        joints, sensors = list(meta["joint_names"]), [s["name"] for s in meta["sensors"]]
        links, kinds = list(meta["slot_links"]), list(meta["slot_kinds"])
        robot = meta["robot"]
        if expect_robot_sha256 is not None and meta["urdf_sha256"] != expect_robot_sha256:
            raise ModelMismatchError(
                f"{path} was exported for robot {robot!r} with URDF sha256 {meta['urdf_sha256']},"
                f" not {expect_robot_sha256}: re-export it for this robot"
            )
        if expect_joint_names is not None and list(expect_joint_names) != joints:
            raise ModelMismatchError(
                f"{path} expects joints {joints} (robot {robot!r}), got {list(expect_joint_names)}"
            )
        if expect_sensors is not None and list(expect_sensors) != sensors:
            raise ModelMismatchError(
                f"{path} expects sensors {sensors}, got {list(expect_sensors)}"
            )
        if expect_slots is not None and (list(expect_slots[0]), list(expect_slots[1])) != (
            links,
            kinds,
        ):
            raise ModelMismatchError(
                f"{path} has contact slots {list(zip(links, kinds, strict=True))}, got"
                f" {list(zip(expect_slots[0], expect_slots[1], strict=True))}"
            )
        names = [i.name for i in self.session.get_inputs()]
        self._inputs = _INPUTS + (_CONE_INPUTS if "constraints" in meta else ())
        if tuple(names) != self._inputs:
            raise ModelMismatchError(f"{path} has inputs {names}, expected {list(self._inputs)}")
        self.joint_names, self.sensor_names = tuple(joints), tuple(sensors)
        self.slot_links, self.slot_kinds = tuple(links), tuple(kinds)
        self.nv, self.S, self.K = len(joints), len(sensors), len(links)
        self.dtype = np.dtype(meta["dtype"])
        self.output_names = [o.name for o in self.session.get_outputs()]
        # single-frame graph: same export (metadata equal but for the batch), static N = 1
        self.step_session = self.session
        name = meta.get("step_graph")
        step_path = os.path.join(os.path.dirname(os.path.abspath(path)), str(name))
        if step_graph and name and os.path.exists(step_path):
            sess = ort.InferenceSession(step_path, so, providers=["CPUExecutionProvider"])
            smeta = dict(sess.get_modelmeta().custom_metadata_map)
            if smeta.pop("batch", None) != "1" or smeta != raw:
                raise ModelMismatchError(
                    f"{step_path} is not the single-frame graph of {path} (re-export both)"
                )
            self.step_session = sess
        self._shapes = {
            "q": (self.nv,),
            "qd": (self.nv,),
            "qdd": (self.nv,),
            "ft": (self.S, 6),
            "positions": (self.K, 3),
            "directions": (self.K, 3),
            "wrenches": (self.K, 6),
            "active": (self.K,),
            "ft_residual": (self.S, 6),
            "normals": (self.K, 3),
            "friction": (self.K,),
            "pushing": (self.K,),
        }
        self._zeros1 = {k: np.zeros((1, *s), self.dtype) for k, s in self._shapes.items()}

    def __repr__(self) -> str:
        return (
            f"EstimatorRuntime({self.path!r}, robot={self.metadata['robot']!r}, nv={self.nv},"
            f" sensors={list(self.sensor_names)}, slots={list(self.slot_kinds)},"
            f" dtype={self.dtype})"
        )

    def _feed(self, values: dict, n: int | None) -> dict[str, np.ndarray]:
        unknown = [k for k, v in values.items() if k not in self._inputs and v is not None]
        if unknown:
            raise ValueError(f"{unknown} are not inputs of {self.path} ({list(self._inputs)})")
        feed = {}
        for k in self._inputs:
            x = values.get(k)
            trailing = self._shapes[k]
            if x is None:
                if k in ("q", "qd", "qdd", "ft", "positions", "normals", "friction"):
                    raise ValueError(f"{k} is required")
                x = (
                    np.ones((1 if n is None else n, *trailing), self.dtype)
                    if k in ("active", "pushing")
                    else (self._zeros1[k] if n is None else np.zeros((n, *trailing), self.dtype))
                )
            else:
                x = np.asarray(x, dtype=self.dtype)
                if n is None:
                    x = x.reshape(1, *x.shape)
                if x.shape[1:] != trailing or (n is not None and x.shape[0] != n):
                    want = ("" if n is None else "(N, ") + ", ".join(map(str, trailing))
                    raise ValueError(
                        f"{k} must have shape {want}{')' if n is not None else ''}"
                        f" (N = {n}), got {x.shape[1:] if n is None else x.shape}"
                    )
            feed[k] = x
        return feed

    def run(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        ft: np.ndarray,
        positions: np.ndarray,
        active: np.ndarray | None = None,
        directions: np.ndarray | None = None,
        wrenches: np.ndarray | None = None,
        ft_residual: np.ndarray | None = None,
        **cones: np.ndarray,
    ) -> dict[str, np.ndarray]:
        """Estimate ``N`` frames.

        Args:
            q: ``(N, nv)`` joint positions, rad or m; ``qd``, ``qdd`` likewise (per second).
            qd: ``(N, nv)`` joint velocities.
            qdd: ``(N, nv)`` joint accelerations.
            ft: ``(N, S, 6)`` F/T readings ``[N; N m]`` in the sensors' frames.
            positions: ``(N, K, 3)`` contact points in the slots' link frames, m.
            active: ``(N, K)`` 1/0 (or bool) slot activity (default all active).
            directions: ``(N, K, 3)`` force directions of ``force_dir`` slots (default zeros).
            wrenches: ``(N, K, 6)`` wrenches of ``known`` slots (default zeros).
            ft_residual: ``(N, S, 6)`` subtracted from ``ft`` (default zeros).
            **cones: a constrained graph's ``normals (N, K, 3)``, ``friction (N, K)`` (both
                required there) and ``pushing (N, K)`` (default ones).

        Returns:
            name -> array: ``force (N, K, 3)`` N, ``moment (N, K, 3)`` N m, ``joint_torques
            (N, nv)``, ``rank``, ``unknowns`` ``(N, S)`` int64, ``residual (N, S)``, ``status
            (N,)`` int64 (0 ok; bits of ``torchcontact.STATUS``); a constrained graph's
            ``converged``, ``iterations`` ``(N, S)`` and ``cone_active (N, K)`` too.
        """
        n = int(np.shape(q)[0])
        values = dict(
            q=q, qd=qd, qdd=qdd, ft=ft, positions=positions, active=active,
            directions=directions, wrenches=wrenches, ft_residual=ft_residual, **cones,
        )  # fmt: skip
        out = self.session.run(None, self._feed(values, n))
        return dict(zip(self.output_names, out, strict=True))

    def step(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        ft: np.ndarray,
        positions: np.ndarray,
        active: np.ndarray | None = None,
        directions: np.ndarray | None = None,
        wrenches: np.ndarray | None = None,
        ft_residual: np.ndarray | None = None,
        **cones: np.ndarray,
    ) -> dict[str, np.ndarray]:
        """Estimate one frame: inputs as :meth:`run` without the leading ``N``; outputs too."""
        values = dict(
            q=q, qd=qd, qdd=qdd, ft=ft, positions=positions, active=active,
            directions=directions, wrenches=wrenches, ft_residual=ft_residual, **cones,
        )  # fmt: skip
        out = self.step_session.run(None, self._feed(values, None))
        return {k: v[0] for k, v in zip(self.output_names, out, strict=True)}
