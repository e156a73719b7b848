"""The live loop: F/T frames + joint states -> estimator -> published results.

Joint states arrive as UDP packets (or from a Python callback). Packet layout, version 1, all
little-endian, no padding (``struct`` format ``<4sHHQqI`` then ``3 n`` float64)::

    offset  size   field
    0       4      magic  b"TCJS"
    4       2      version (uint16) = 1
    6       2      reserved (uint16) = 0
    8       8      seq (uint64), increasing per packet
    16      8      t_ns (int64), sender's monotonic time, ns
    24      4      n (uint32), number of joints
    28      8 n    q    (float64[n]), rad or m
    28+8n   8 n    qd   (float64[n]), rad/s or m/s
    28+16n  8 n    qdd  (float64[n]), rad/s^2 or m/s^2

For every new F/T sample the loop takes the newest joint state, calls
``estimator(q, qd, qdd, ft) -> dict`` and publishes one JSON object per line
(``{"t_ns", "seq", "ft", "joint_seq", "estimate", "latency_us"}``) to stdout or UDP, optionally
logging the frames to Parquet. Latency is measured from the sample's timestamp (host time the
frame was received) to the moment its result was handed to the publishers.
"""

from __future__ import annotations

import importlib
import json
import math
import socket
import struct
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TextIO

import numpy as np

from torchcontact.drivers.base import FTSample, FTSource
from torchcontact.drivers.log import FTLogWriter
from torchcontact.errors import InputError, ModelMismatchError
from torchcontact.onnx import format as fmt

MAGIC = b"TCJS"
VERSION = 1
_HEADER = struct.Struct("<4sHHQqI")


@dataclass(frozen=True)
class JointState:
    """Joint positions, velocities, accelerations at one instant.

    Attributes:
        seq: Sender's sequence number.
        t_ns: Sender's monotonic time, ns.
        q: (n,) float64 positions, rad (revolute) or m (prismatic).
        qd: (n,) float64 velocities.
        qdd: (n,) float64 accelerations.
    """

    seq: int
    t_ns: int
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray


def pack_joint_state(seq: int, t_ns: int, q: Any, qd: Any, qdd: Any) -> bytes:
    """Encode a joint-state UDP packet (layout in the module docstring).

    Args:
        seq: Sequence number (uint64).
        t_ns: Time, ns (int64).
        q: (n,) positions, rad or m.
        qd: (n,) velocities.
        qdd: (n,) accelerations.

    Returns:
        The packet, ``28 + 24 n`` bytes.

    Raises:
        ValueError: If the three arrays differ in length.

    Example:
        >>> p = pack_joint_state(7, 123, [0.1, 0.2], [0.0, 0.0], [1.0, -1.0])
        >>> len(p), p[:4]
        (76, b'TCJS')
        >>> unpack_joint_state(p).qdd
        array([ 1., -1.])
    """
    arrays = [np.asarray(a, dtype="<f8").reshape(-1) for a in (q, qd, qdd)]
    n = len(arrays[0])
    if any(len(a) != n for a in arrays):
        raise ValueError(f"q, qd, qdd must have the same length, got {[len(a) for a in arrays]}")
    return _HEADER.pack(MAGIC, VERSION, 0, seq, t_ns, n) + b"".join(a.tobytes() for a in arrays)


def unpack_joint_state(packet: bytes) -> JointState:
    """Decode a joint-state UDP packet.

    Raises:
        ValueError: Naming what is wrong: short packet, magic, version, or length.
    """
    if len(packet) < _HEADER.size:
        raise ValueError(f"joint packet of {len(packet)} bytes is shorter than its header (28)")
    magic, version, _, seq, t_ns, n = _HEADER.unpack_from(packet)
    if magic != MAGIC:
        raise ValueError(f"joint packet magic {magic!r} != {MAGIC!r}")
    if version != VERSION:
        raise ValueError(f"joint packet version {version} not supported (expected {VERSION})")
    if len(packet) != _HEADER.size + 24 * n:
        raise ValueError(f"joint packet has {len(packet)} bytes, expected {28 + 24 * n} (n={n})")
    data = np.frombuffer(packet, dtype="<f8", offset=_HEADER.size).astype(np.float64)
    return JointState(seq, t_ns, data[:n], data[n : 2 * n], data[2 * n :])


class UdpJointSource:
    """Receive joint-state packets on a UDP socket; calling it returns the newest one.

    Old (``seq`` not increasing) and malformed packets are dropped and counted.

    Args:
        host: Address to bind (loopback by default).
        port: Port; 0 picks a free one (see :attr:`address`).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.sock.setblocking(False)
        self.address: tuple[str, int] = self.sock.getsockname()
        self.latest: JointState | None = None
        self.received = 0
        self.rejected = 0
        self.stale = 0

    def __call__(self) -> JointState | None:
        """Drain the socket and return the newest valid joint state (or the last one seen)."""
        while True:
            try:
                packet = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return self.latest
            try:
                js = unpack_joint_state(packet)
            except ValueError:
                self.rejected += 1
                continue
            if self.latest is not None and js.seq <= self.latest.seq:
                self.stale += 1
                continue
            self.received += 1
            self.latest = js

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()


class Publisher(Protocol):
    """Anything that takes one result dict."""

    def publish(self, record: dict[str, Any]) -> None:
        """Publish one result."""


def _jsonable(x: Any) -> Any:
    """Plain JSON values: arrays as lists, and NaN or infinite numbers as None (JSON null)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "detach"):  # torch tensor, without importing torch
        x = x.detach().cpu().numpy()
    if isinstance(x, np.ndarray):
        if x.dtype.kind == "f" and np.isfinite(x).all():
            return x.tolist()
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def json_line(record: Any) -> str:
    """One line of strict JSON (RFC 8259): NaN and infinities become ``null``.

    Python's ``json`` writes bare ``NaN``, which strict parsers (JavaScript, Go, serde, jq)
    reject; a torque a ``--joints sensed`` graph does not compute is NaN.

    Example:
        >>> json_line({"tau": np.array([1.0, np.nan]), "x": float("inf")})
        '{"tau":[1.0,null],"x":null}'
    """
    return json.dumps(_jsonable(record), separators=(",", ":"), allow_nan=False)


class JsonLinesPublisher:
    """Write each result as one JSON line to a text stream (stdout by default)."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream if stream is not None else sys.stdout

    def publish(self, record: dict[str, Any]) -> None:
        """Write one line and flush."""
        self.stream.write(json_line(record) + "\n")
        self.stream.flush()


class UdpPublisher:
    """Send each result as one JSON datagram (UTF-8, newline-terminated).

    Args:
        host: Destination host; must be a loopback address unless ``allow_remote``.
        port: Destination port.
        allow_remote: Permit a non-loopback destination.

    Raises:
        ValueError: If ``host`` is not loopback and ``allow_remote`` is false.
    """

    def __init__(self, host: str, port: int, allow_remote: bool = False) -> None:
        if not allow_remote and not (host == "localhost" or host.startswith("127.")):
            raise ValueError(f"refusing to publish to {host}: loopback only (allow_remote=True)")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.dest = (host, port)

    def publish(self, record: dict[str, Any]) -> None:
        """Send one datagram (dropped silently by the OS if nobody listens)."""
        data = (json_line(record) + "\n").encode()
        try:
            self.sock.sendto(data, self.dest)
        except OSError:
            pass

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()


Estimator = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], dict[str, Any]]


def load_estimator(spec: str) -> Estimator:
    """Import an estimator given as ``module:function``.

    Raises:
        ValueError: If the spec is malformed, the module or attribute is missing, or it is not
            callable.

    Example:
        >>> load_estimator("torchcontact.drivers.live:passthrough_estimator").__name__
        'passthrough_estimator'
    """
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"--estimator must be module:function, got {spec!r}")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"cannot import estimator module {module_name!r}: {exc}") from exc
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise ValueError(f"{module_name!r} has no callable {attr!r}")
    return fn


def passthrough_estimator(
    q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, ft: np.ndarray
) -> dict[str, Any]:
    """Trivial estimator: returns the measured wrench and its force norm.

    Args:
        q: (n,) joint positions, rad or m.
        qd: (n,) joint velocities.
        qdd: (n,) joint accelerations.
        ft: (6,) [force; moment] in N and N m, sensor frame.

    Returns:
        ``{"wrench": ft, "force_norm": |f|}`` (N).
    """
    return {"wrench": ft, "force_norm": float(np.linalg.norm(ft[:3]))}


ContactSpec = Callable[[np.ndarray], dict[str, Any]]


class SensorGroup(FTSource):
    """Several F/T sources read as one: each sample of the first carries the latest of all.

    The first source sets the pace (one sample of the group per sample of it); each other source
    is read once without waiting (a polled sensor answers with its current value, a streaming one
    with its next queued frame) and its latest reading is attached. Samples are withheld until
    every source has delivered once. Its samples' ``wrench`` is ``(6 S,)``, sources in order.

    Args:
        sources: the sources, opened or not; the first drives the loop.
    """

    def __init__(self, sources: Sequence[FTSource]) -> None:
        if not sources:
            raise ValueError("SensorGroup needs at least one source")
        super().__init__(sources[0].name)
        self.sources = list(sources)
        self._latest: list[np.ndarray | None] = [None] * len(self.sources)
        self.stats = self.sources[0].stats

    def describe(self) -> str:
        """The sources, in order."""
        return ", ".join(s.describe() for s in self.sources)

    def _connect(self) -> None:
        for s in self.sources:
            if not s.connected:
                s.open()

    def _disconnect(self) -> None:
        for s in self.sources:
            s.close()

    def _receive(self, timeout: float):  # pragma: no cover - read() is overridden
        raise NotImplementedError

    def open(self) -> None:
        """Open every source."""
        self._connect()
        self._connected = True

    def close(self) -> None:
        """Close every source."""
        self._disconnect()
        self._connected = False

    def read(self, timeout: float = 0.1) -> FTSample | None:
        """The next sample of the first source with the newest of the others, or None."""
        for i, s in enumerate(self.sources[1:], start=1):
            x = s.read(0.0)
            if x is not None:
                self._latest[i] = x.wrench
        first = self.sources[0].read(timeout)
        if first is None:
            return None
        self._latest[0] = first.wrench
        if any(w is None for w in self._latest):
            return None
        return FTSample(first.t_ns, first.seq, np.concatenate(self._latest), first.flags)


class OnnxEstimator:
    """The exported contact estimator (ONNX, onnxruntime) as a live-loop estimator.

    Wraps :class:`torchcontact.runtime.EstimatorRuntime` (numpy and onnxruntime only, no torch):
    each call estimates one frame from the joint state and the readings of the graph's F/T
    sensors (``(6 S,)``, sensors in the graph's order, e.g. from a :class:`SensorGroup`).
    Contact positions and activity, and any other per-frame input of the graph, come from
    ``contacts``:

    - ``None``: every slot inactive (no contact; the estimate then explains nothing and the
      forces are zero, while the F/T residual shows any unexplained load);
    - a dict with ``positions (K, 3)`` m in each slot's link frame, ``active (K,)`` and optionally
      ``directions (K, 3)`` (``force_dir`` slots), ``wrenches (K, 6)`` (``known`` slots), and the
      graph's other inputs (``omega``, ``domega``, ``proper_acc``, ``tau_measured``,
      ``tau_mask``, ``ft_cov``, ``extra``: a dict of the residual corrections' extra columns);
    - a callable ``contacts(q) -> dict`` as above, called every frame (e.g. from a tactile skin).

    Args:
        path: ``.onnx`` file from ``python -m export estimator``.
        contacts: the contact spec above.
        robot: the robot the joint states come from (URDF path, ``"tcarm"`` or a model): a graph
            exported for another robot is refused.
        residual: residual-correction graph(s) to chain before the estimator.
        expect_joint_names: refuse a graph with another joint order (the joint-state sender's).
        intra_op_threads: onnxruntime threads (1: lowest single-frame latency).

    Raises:
        torchcontact.runtime.ModelMismatchError: not an estimator graph, or another robot.
        ValueError: a contact spec of the wrong shape.
    """

    def __init__(
        self,
        path: str,
        contacts: dict[str, Any] | ContactSpec | None = None,
        *,
        robot: Any = None,
        residual: Any = None,
        expect_joint_names: Sequence[str] | None = None,
        intra_op_threads: int = 1,
    ) -> None:
        import os

        from torchcontact.runtime import EstimatorRuntime

        if not os.path.isfile(path):
            raise InputError(f"--onnx {path}: no such file")
        self.runtime = EstimatorRuntime(
            path,
            robot,
            residual=residual,
            expect_joint_names=expect_joint_names,
            intra_op_threads=intra_op_threads,
        )
        rt = self.runtime
        self.contacts = contacts
        self._fixed = None
        if contacts is None:
            self._fixed = {"positions": np.zeros((rt.K, 3)), "active": np.zeros(rt.K)}
        elif not callable(contacts):
            self._fixed = self._check(contacts)

    def set_inputs(self, spec: dict[str, Any]) -> None:
        """Use ``spec`` (the dict form of ``contacts`` above) for every following frame.

        Raises:
            InputError: a key the graph does not take or a value of the wrong shape.
        """
        self.contacts = spec
        self._fixed = self._check(spec)

    #: The inputs a contact spec may hold (the names of :data:`torchcontact.onnx.format.INPUTS`
    #: besides the joint state, the readings and the friction-cone inputs).
    _KEYS = tuple(
        i.name
        for i in fmt.INPUTS
        if i.name not in ("q", "qd", "qdd", "ft", "ft_residual", *fmt.CONE_INPUTS)
    )

    def _check(self, spec: dict[str, Any]) -> dict[str, Any]:
        rt = self.runtime
        dims = {"K": rt.K, "S": rt.S, "nv": rt.nv}
        shapes = {
            i.name: tuple(dims[d] if d in dims else int(d) for d in i.shape.split(", "))
            for i in fmt.INPUTS
            if i.name in self._KEYS and i.name != fmt.EXTRA
        }
        out: dict[str, Any] = {}
        for name, value in spec.items():
            key = fmt.canonical(name)
            if key not in self._KEYS:
                raise ValueError(f"contact spec key {name!r} not one of {list(self._KEYS)}")
            if key == "extra":
                out[key] = {str(k): float(v) for k, v in dict(value).items()}
                continue
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape != shapes[key]:
                raise ValueError(
                    f"contact spec {key} must have shape {shapes[key]}, got {arr.shape}"
                )
            out[key] = arr
        if "positions" not in out:
            raise ValueError("contact spec needs positions (K, 3)")
        out.setdefault("active", np.ones(rt.K))
        return out

    def __call__(
        self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, ft: np.ndarray
    ) -> dict[str, Any]:
        """Estimate one frame.

        Args:
            q: ``(nv,)`` joint positions in the graph's joint order, rad or m.
            qd: ``(nv,)`` joint velocities.
            qdd: ``(nv,)`` joint accelerations.
            ft: ``(6 S,)`` or ``(S, 6)`` readings ``[N; N m]`` in the sensors' frames, raw.

        Returns:
            ``force (K, 3)`` N and ``moment (K, 3)`` N m in each slot's link frame,
            ``joint_torques (nv,)``, ``rank``, ``unknowns``, ``residual`` ``(S,)`` and ``status``
            (0: ok), numpy arrays.

        Raises:
            ModelMismatchError: the joint state does not have the graph's joint count (another
                robot: fatal, the loop stops).
            ValueError: a malformed reading or contact spec.
        """
        from torchcontact.runtime import ModelMismatchError

        rt = self.runtime
        if len(q) != rt.nv:
            raise ModelMismatchError(
                f"joint state has {len(q)} joints, the graph expects {rt.nv}"
                f" ({rt.metadata['robot']}: {list(rt.joint_names)})"
            )
        ft = np.asarray(ft, dtype=np.float64)
        if ft.size != 6 * rt.S:
            raise ValueError(
                f"reading has {ft.size} values, the graph reads {rt.S} sensors"
                f" {list(rt.sensor_names)} (6 each)"
            )
        spec = self._fixed if self._fixed is not None else self._check(self.contacts(q))  # type: ignore[misc]
        return rt.step({**spec, "q": q, "qd": qd, "qdd": qdd, "ft": ft.reshape(rt.S, 6)})


class LiveLoop:
    """Drive an estimator from an F/T source and a joint-state source.

    Args:
        ft_source: An opened or unopened :class:`~torchcontact.drivers.base.FTSource`.
        joint_source: Callable returning the newest :class:`JointState` (or ``None``), e.g. a
            :class:`UdpJointSource`; ``None`` runs without joints (empty arrays).
        estimator: ``estimator(q, qd, qdd, ft) -> dict``.
        publishers: Objects with ``publish(record)``.
        log: Optional Parquet log of the F/T frames.
        require_joints: Skip frames until a joint state has arrived.
        latency_window: Number of recent latencies kept for the statistics.
        on_frame: Called as ``on_frame(sample, joint_state, estimate)`` after each frame is
            published (e.g. :class:`torchcontact.view.LiveView` for ``run --view``).
    """

    def __init__(
        self,
        ft_source: FTSource,
        joint_source: Callable[[], JointState | None] | None,
        estimator: Estimator,
        publishers: Sequence[Publisher],
        *,
        log: FTLogWriter | None = None,
        require_joints: bool = False,
        latency_window: int = 100_000,
        on_frame: Callable[[FTSample, JointState | None, dict[str, Any]], None] | None = None,
    ) -> None:
        self.on_frame = on_frame
        self.ft = ft_source
        self.joints = joint_source
        self.estimator = estimator
        self.publishers = list(publishers)
        self.log = log
        self.require_joints = require_joints
        self.latencies_ns: deque[int] = deque(maxlen=latency_window)
        self.published = 0
        self.skipped_no_joints = 0
        self.estimator_errors = 0
        self._empty = np.zeros(0)

    def step(self, timeout: float = 0.1) -> dict[str, Any] | None:
        """Process at most one F/T sample; return the published record or ``None``."""
        sample = self.ft.read(timeout)
        if sample is None:
            return None
        if self.log is not None:
            self.log.append(sample.t_ns, sample.wrench)
        js = self.joints() if self.joints is not None else None
        if js is None and self.require_joints:
            self.skipped_no_joints += 1
            return None
        q, qd, qdd = (js.q, js.qd, js.qdd) if js is not None else (self._empty,) * 3
        try:
            estimate = self.estimator(q, qd, qdd, sample.wrench)
        except ModelMismatchError:
            raise  # another robot: every frame would fail, stop with one error
        except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the loop
            self.estimator_errors += 1
            estimate = {"error": f"{type(exc).__name__}: {exc}"}
        record = {
            "t_ns": sample.t_ns,
            "seq": sample.seq,
            "flags": int(sample.flags),
            "ft": sample.wrench,
            "joint_seq": js.seq if js is not None else None,
            "estimate": estimate,
        }
        latency = time.monotonic_ns() - sample.t_ns
        record["latency_us"] = latency / 1e3
        record = _jsonable(record)
        for pub in self.publishers:
            pub.publish(record)
        if self.on_frame is not None:
            self.on_frame(sample, js, estimate)
        self.latencies_ns.append(latency)
        self.published += 1
        return record

    def run(self, duration: float | None = None, max_frames: int | None = None) -> dict[str, Any]:
        """Loop until ``duration`` seconds passed or ``max_frames`` were published.

        Returns:
            :meth:`summary`.
        """
        end = time.monotonic() + duration if duration is not None else float("inf")
        try:
            while time.monotonic() < end and (max_frames is None or self.published < max_frames):
                self.step(timeout=min(0.1, max(0.0, end - time.monotonic())) or 0.01)
        except KeyboardInterrupt:
            pass
        return self.summary()

    def summary(self) -> dict[str, Any]:
        """Counters and latency percentiles (µs) of the frames published so far."""
        lat = np.asarray(self.latencies_ns, dtype=np.float64) / 1e3
        pct = {
            f"latency_p{p}_us": float(np.percentile(lat, p)) if len(lat) else None for p in (50, 99)
        }
        return {
            "published": self.published,
            "skipped_no_joints": self.skipped_no_joints,
            "estimator_errors": self.estimator_errors,
            **pct,
            "latency_max_us": float(lat.max()) if len(lat) else None,
            "ft": self.ft.stats.as_dict(),
        }
