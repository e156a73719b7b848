"""Run a C step library (:func:`torchcontact.online.cstep.export_c_step`) with ctypes and numpy.

No torch, no onnxruntime: the library is the whole single-frame estimator with its offset and
inertial correction; this module fills its packed input vector, calls it, and keeps the online
state between frames (:class:`~torchcontact.online.state.OnlineState`: the tracked bias, the
payload, a running payload identification). It becomes ``EstimatorRuntime(..., backend="c")``
once the deployment wing (``torchcontact/onnx/``) lands.

Use (``arm.so`` from ``torchcontact export estimator --format c``; tested in tests/online)::

    rt = CStepRuntime("arm.so", robot="tcarm", track_bias=True)
    out = rt.step(q, qd, qdd, ft, positions, active)
    out["force"], out["bias"].offset  # (K, 3) N; (S, 6) tracked offsets
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import InputError, ModelMismatchError
from torchcontact.online.bias import BiasState, BiasTracker
from torchcontact.online.payload import Payload
from torchcontact.online.state import OnlineState, SensorLayout

__all__ = ["C_FORMAT", "CStepRuntime", "robot_sha256"]

#: ``metadata["format"]`` this loader reads (:data:`torchcontact.online.cstep.C_FORMAT`).
C_FORMAT = "torchcontact.cstep/1"
_ABI = 1


def robot_sha256(robot: Any) -> tuple[str, tuple[str, ...] | None]:
    """URDF sha256 (and joint names, for a model) of ``robot``, without torch or onnxruntime.

    The identity the ONNX graphs carry today (``urdf_sha256``, see
    ``torchcontact.runtime.robot_identity``, which needs onnxruntime to import).

    Args:
        robot: a ``RobotModel`` (anything with ``urdf_sha256``), a URDF path, or ``"tcarm"``.

    Raises:
        ModelMismatchError: no such URDF file.
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


class CStepRuntime:
    """A C step library loaded for inference, with bias tracking and payloads.

    Args:
        path: the library ``NAME.so``.
        robot: the robot the caller runs (URDF path, ``"tcarm"`` or a model): a library exported
            for another URDF (sha256) or joint order is refused.
        prefix: the library's symbol prefix (``export_c_step(prefix=...)``).
        track_bias: track each sensor's offset on contact-free frames: True (a
            :class:`~torchcontact.online.bias.BiasTracker` with ``tracker_options``), a tracker,
            or False (offsets change only by :meth:`tare` and :meth:`identify_payload`).
        tracker_options: :class:`BiasTracker` keyword arguments (``time_constant``, ``period``,
            ``ft_std``, ``gate``, ...).
        expect_joint_names: refuse the library unless its joint order matches.
        expect_sensors: refuse it unless its sensors (in order) match.
        expect_slots: refuse it unless its ``(links, kinds)`` match.

    Attributes:
        metadata: the library's metadata (JSON decoded).
        nv, S, K: joints, sensors, slots; joint_names, sensor_names, slot_links, slot_kinds.
        state: the :class:`~torchcontact.online.state.OnlineState`.

    Raises:
        InputError: no such file.
        ModelMismatchError: not a C step library of this format, or a check fails.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        robot: Any = None,
        *,
        prefix: str = "tc_estimator",
        track_bias: bool | BiasTracker = False,
        tracker_options: Mapping[str, Any] | None = None,
        expect_joint_names: Sequence[str] | None = None,
        expect_sensors: Sequence[str] | None = None,
        expect_slots: tuple[Sequence[str], Sequence[str]] | None = None,
    ) -> None:
        p = Path(os.fspath(path))
        if not p.is_file():
            raise InputError(f"{p}: no such file")
        try:
            lib = ctypes.CDLL(str(p.resolve()))
            meta_fn = getattr(lib, f"{prefix}_metadata")
            abi = getattr(lib, f"{prefix}_abi")
        except (OSError, AttributeError) as e:
            raise ModelMismatchError(
                f"{p} is not a torchcontact C step library with prefix {prefix!r} ({e})"
            ) from None
        meta_fn.restype = ctypes.c_char_p
        meta = json.loads(meta_fn().decode())
        if meta.get("format") != C_FORMAT or abi() != _ABI:
            raise ModelMismatchError(
                f"{p} is a C step of format {meta.get('format')!r}, ABI {abi()}; this loader reads"
                f" {C_FORMAT!r}, ABI {_ABI}: re-export it"
            )
        self.path, self.metadata, self._lib = str(p), meta, lib
        self.joint_names = tuple(meta["joint_names"])
        self.sensor_names = tuple(s["name"] for s in meta["sensors"])
        self.slot_links, self.slot_kinds = tuple(meta["slot_links"]), tuple(meta["slot_kinds"])
        self.nv, self.S, self.K = (
            len(self.joint_names),
            len(self.sensor_names),
            len(self.slot_links),
        )
        self.dtype = np.dtype(meta["dtype"])
        self._check(robot, expect_joint_names, expect_sensors, expect_slots)
        # the packed vectors, their field views, and the call with fixed pointers
        self._x = np.zeros(meta["in_size"], self.dtype)
        self._out = np.zeros(meta["out_size"], self.dtype)
        ptr = ctypes.POINTER(ctypes.c_double if self.dtype == np.float64 else ctypes.c_float)
        defaults = getattr(lib, f"{prefix}_defaults")
        defaults.argtypes, defaults.restype = [ptr], None
        defaults(self._x.ctypes.data_as(ptr))
        self._x0 = self._x.copy()
        self._in = {k: self._view(self._x, o, sh) for k, (o, sh) in meta["inputs"].items()}
        self.outputs = {k: self._view(self._out, o, sh) for k, (o, sh) in meta["outputs"].items()}
        step = getattr(lib, f"{prefix}_step")
        step.argtypes, step.restype = [ctypes.c_void_p, ctypes.c_void_p], ctypes.c_int
        run = getattr(lib, f"{prefix}_run")
        run.restype = None
        run.argtypes = [ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p,
                        ctypes.c_int64]  # fmt: skip
        self._step_fn, self._run_fn = step, run
        self._xp, self._op = self._x.ctypes.data, self._out.ctypes.data
        # the online state: offsets start at the correction stack's (the library's defaults)
        layouts = [
            SensorLayout(
                o["sensor"],
                tuple(o["body_index"]),
                {
                    k: (b, np.asarray(R).reshape(3, 3), np.asarray(t))
                    for k, (b, R, t) in o["frames"].items()
                },
                o["payload_link"],
                self._in[f"theta.{o['sensor']}"].astype(np.float64).copy(),
            )  # fmt: skip
            for o in meta["online"]
        ]
        opts = dict(tracker_options or {})
        tracker = track_bias if isinstance(track_bias, BiasTracker) else None
        if tracker is None:
            opts.setdefault("offset", self._in["bias"].astype(np.float64).copy())
            tracker = BiasTracker(self.sensor_names, **opts)
        self.state = OnlineState(layouts, meta["slot_regions"], tracker, track=bool(track_bias))
        self._fresh: set[str] = set()
        tj = list(meta["torque_joints"])
        self._tau_idx = None if tj == list(self.joint_names) else [
            self.joint_names.index(j) for j in tj
        ]  # fmt: skip

    @staticmethod
    def _view(buf: np.ndarray, off: int, shape: Sequence[int]) -> np.ndarray:
        n = int(np.prod(shape))
        return buf[off : off + n].reshape(tuple(shape))

    def _check(self, robot, joints, sensors, slots) -> None:
        meta, path = self.metadata, self.path
        if robot is not None:
            h, names = robot_sha256(robot)
            if h != meta["urdf_sha256"]:
                raise ModelMismatchError(
                    f"{path} was exported for robot {meta['robot']!r} (URDF sha256"
                    f" {meta['urdf_sha256'][:12]}...), not for this robot (sha256 {h[:12]}...):"
                    " re-export it for this robot"
                )
            joints = joints if names is None else names
        if joints is not None and tuple(joints) != self.joint_names:
            raise ModelMismatchError(
                f"{path} expects joints {list(self.joint_names)} (robot {meta['robot']!r}), got"
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
                f"{path} has contact slots {have}, got {list(zip(*slots, strict=True))}"
            )

    def __repr__(self) -> str:
        return (
            f"CStepRuntime({self.path!r}, robot={self.metadata['robot']!r}, nv={self.nv},"
            f" sensors={list(self.sensor_names)}, slots={list(self.slot_kinds)},"
            f" dtype={self.dtype})"
        )

    # ------------------------------------------------------------------------------- inputs
    def _put(self, name: str, value: Any, default: float | None = 0.0) -> None:
        view = self._in.get(name)
        if view is None:
            if value is not None:
                raise InputError(f"this library has no input {name!r} (exported without it)")
            return
        if value is None:
            if default is None:
                raise InputError(f"{name} is required, shape {view.shape}")
            if name not in self._fresh:
                view[...] = default
                self._fresh.add(name)
            return
        self._fresh.discard(name)
        if type(value) is np.ndarray and value.shape == view.shape:
            view[...] = value
            return
        arr = np.asarray(value, dtype=np.float64)
        if arr.shape != view.shape:
            if arr.size != view.size:
                raise InputError(f"{name} must have shape {view.shape}, got {arr.shape}")
            arr = arr.reshape(view.shape)
        view[...] = arr

    def _ft(self, ft: Any) -> np.ndarray:
        if type(ft) is np.ndarray and ft.shape == (self.S, 6) and ft.dtype == np.float64:
            return ft
        if isinstance(ft, Mapping):
            missing = [s for s in self.sensor_names if s not in ft]
            if missing:
                raise InputError(f"ft is missing readings of sensors {missing}")
            return np.stack([np.asarray(ft[s], dtype=np.float64).reshape(6) for s in
                             self.sensor_names])  # fmt: skip
        arr = np.asarray(ft, dtype=np.float64)
        if arr.size != 6 * self.S:
            raise InputError(f"ft must be ({self.S}, 6), got {arr.shape}")
        return arr.reshape(self.S, 6)

    # ---------------------------------------------------------------------------- one frame
    def step(
        self,
        q: Any,
        qd: Any,
        qdd: Any,
        ft: Any,
        positions: Any = None,
        active: Any = None,
        directions: Any = None,
        wrenches: Any = None,
        *,
        omega: Any = None,
        domega: Any = None,
        proper_acc: Any = None,
        tau_measured: Any = None,
        tau_mask: Any = None,
        ft_cov: Any = None,
        contact_free: Any = None,
        t: float | None = None,
    ) -> dict[str, Any]:
        """Estimate one frame from the raw readings, then update the online state.

        Args:
            q: ``(nv,)`` joint positions in :attr:`joint_names` order, rad or m.
            qd: ``(nv,)`` velocities.
            qdd: ``(nv,)`` accelerations.
            ft: ``(S, 6)`` raw readings ``[N; N m]``, or sensor name -> ``(6,)``.
            positions: ``(K, 3)`` contact points, slot link frames, m (default zeros).
            active: ``(K,)`` 1/0 slot activity (default all active, as ``EstimatorRuntime``; pass it
                when tracking the bias: only sensors without an active slot are updated).
            directions: ``(K, 3)`` of ``force_dir`` slots.
            wrenches: ``(K, 6)`` of ``known`` slots.
            omega: ``(3,)`` rad/s (moving base).
            domega: ``(3,)`` rad/s^2 (moving base).
            proper_acc: ``(3,)`` m/s^2 (moving base).
            tau_measured: ``(nv,)`` (torque rows).
            tau_mask: ``(nv,)`` (default: the finite torques).
            ft_cov: ``(S, 6, 6)`` (covariance).
            contact_free: the caller's contact-free signal for the bias tracker (bool or
                ``(S,)``; see :meth:`OnlineState.contact_free`).
            t: the frame's time, s (the tracker's clock; None: one nominal period on).

        Returns:
            ``force``, ``moment`` ``(K, 3)``, ``joint_torques (nv,)`` (NaN for the joints the
            library was exported without, ``metadata["torque_joints"]``, as the ONNX graphs),
            ``rank``, ``unknowns`` ``(S,)`` int64,
            ``residual (S,)``, ``status`` (int), ``covariance (K, 6, 6)`` when exported,
            ``ft_model (S, 6)`` and ``bias`` (:class:`BiasState` after the frame). The arrays
            are copies.

        Raises:
            InputError: a wrong shape or a missing required input.
        """
        st = self.state
        ftv = self._ft(ft)
        put = self._put
        put("q", q, None)
        put("qd", qd, None)
        put("qdd", qdd, None)
        self._in["ft"][...] = ftv
        put("positions", positions)
        put("active", active, 1.0)
        put("directions", directions)
        put("wrenches", wrenches)
        if "omega" in self._in or omega is not None:
            put("omega", omega, None)
            put("domega", domega, None)
            put("proper_acc", proper_acc, None)
        if "tau_measured" in self._in or tau_measured is not None:
            put("tau_measured", tau_measured, None)
            if tau_mask is None:
                tau_mask = np.isfinite(np.asarray(tau_measured, dtype=float))
            put("tau_mask", tau_mask, None)
        if "ft_cov" in self._in or ft_cov is not None:
            put("ft_cov", ft_cov, None)
        self._in["bias"][...] = st.bias()
        status = self._step_fn(self._xp, self._op)
        o = self.outputs
        ft_model = o["ft_model"].astype(np.float64)
        free = st.contact_free(self._in["active"], contact_free)
        if status:
            free[:] = False
        regs = None
        if any(i is not None for i in st.identifiers):  # only a running identification needs them
            regs = [o[f"regressor.{s}"].astype(np.float64) for s in self.sensor_names]
        bias = st.after_step(ftv, ft_model, free, regs, t)
        res = {
            "force": o["force"].copy(),
            "moment": o["moment"].copy(),
            "joint_torques": self._torques(o["joint_torques"]),
            "rank": o["rank"].astype(np.int64),
            "unknowns": o["unknowns"].astype(np.int64),
            "residual": o["residual"].copy(),
            "status": int(status),
            "ft_model": ft_model,
            "bias": bias,
        }
        if "covariance" in o:
            res["covariance"] = o["covariance"].copy()
        return res

    def _torques(self, tau: np.ndarray) -> np.ndarray:
        if self._tau_idx is None:
            return tau.astype(np.float64)
        out = np.full(self.nv, np.nan)
        out[self._tau_idx] = tau
        return out

    def step_raw(self) -> int:
        """Call the library on the packed input as it stands (no Python work; benchmarks)."""
        return self._step_fn(self._xp, self._op)

    # --------------------------------------------------------------------------- many frames
    def run(self, x: np.ndarray) -> np.ndarray:
        """Estimate ``N`` packed frames, rows of ``x`` ``(N, in_size)``; returns ``(N, out_size)``.

        Fields are at ``metadata["inputs"]`` / ``["outputs"]`` offsets; no online state is used
        or updated (use :meth:`pack` to build ``x``).
        """
        x = np.ascontiguousarray(x, dtype=self.dtype)
        if x.ndim != 2 or x.shape[1] != self._x.size:
            raise InputError(f"x must be (N, {self._x.size}), got {x.shape}")
        out = np.empty((x.shape[0], self._out.size), self.dtype)
        self._run_fn(x.shape[0], x.ctypes.data, x.shape[1], out.ctypes.data, out.shape[1])
        return out

    def pack(self, n: int, **fields: Any) -> np.ndarray:
        """``(n, in_size)`` packed inputs for :meth:`run`.

        The defaults (with the current bias and theta), then each given field ``(n, *shape)``
        (names of ``metadata["inputs"]``).
        """
        x = np.broadcast_to(self._x0, (n, self._x0.size)).copy()
        meta = self.metadata["inputs"]
        o = meta["bias"][0]
        x[:, o : o + 6 * self.S] = self.state.bias().reshape(-1)
        for i, s in enumerate(self.sensor_names):
            o, sh = meta[f"theta.{s}"]
            x[:, o : o + sh[0]] = self.state.theta(i)
        for k, v in fields.items():
            if k not in meta:
                raise InputError(f"unknown input {k!r}; the library has {list(meta)}")
            o, sh = meta[k]
            size = int(np.prod(sh))
            x[:, o : o + size] = np.asarray(v, dtype=np.float64).reshape(n, size)
        return x

    def unpack(self, out: np.ndarray) -> dict[str, np.ndarray]:
        """Output fields ``(N, *shape)`` of :meth:`run`'s result."""
        n = out.shape[0]
        return {k: out[:, o : o + int(np.prod(sh))].reshape(n, *sh)
                for k, (o, sh) in self.metadata["outputs"].items()}  # fmt: skip

    # ------------------------------------------------------------------------------ commands
    def tare(self, frames: int = 1) -> BiasState:
        """Re-zero the offsets now, at the current pose, from the model.

        See :meth:`OnlineState.tare`; refused while a contact is active.
        """
        return self.state.tare(frames)

    def set_payload(
        self,
        mass: float | Payload | None,
        com: Any = (0.0, 0.0, 0.0),
        inertia: Any = None,
        *,
        link: str | None = None,
        sensor: str | None = None,
    ) -> Payload | None:
        """A tool change: the payload a sensor carries from the next frame on.

        Args:
            mass: kg, or a :class:`Payload`, or None (no payload).
            com: ``(3,)`` centre of mass in ``link``'s frame, m.
            inertia: ``(3, 3)`` about the centre of mass, link axes, kg m^2 (default: a point).
            link: the link it is attached to (default: the sensor's payload link).
            sensor: the sensor (None: the only one).

        Raises:
            InputError: a non-physical payload, a link the sensor does not carry.
        """
        if mass is None or isinstance(mass, Payload):
            payload = mass
        else:
            payload = Payload(mass, com, np.zeros((3, 3)) if inertia is None else inertia, link)
        self.state.set_payload(payload, sensor)
        i = self.state.index(sensor)
        self._in[f"theta.{self.sensor_names[i]}"][...] = self.state.theta(i)
        return self.state.payloads[i]

    def start_identification(self, sensor: str | None = None, **kwargs: Any) -> None:
        """Identify the payload from the next contact-free frames.

        See :meth:`OnlineState.start_identification`.
        """
        self.state.start_identification(sensor, **kwargs)
        i = self.state.index(sensor)
        self._in[f"theta.{self.sensor_names[i]}"][...] = self.state.theta(i)

    def identify_payload(self, sensor: str | None = None, apply: bool = True) -> Payload:
        """The identified payload (refused until the data identify it), applied by default."""
        p = self.state.identify_payload(sensor, apply)
        i = self.state.index(sensor)
        self._in[f"theta.{self.sensor_names[i]}"][...] = self.state.theta(i)
        return p
