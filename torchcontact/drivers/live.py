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
import socket
import struct
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TextIO

import numpy as np

from torchcontact.drivers.base import FTSource
from torchcontact.drivers.log import FTLogWriter

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
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "detach"):  # torch tensor, without importing torch
        x = x.detach().cpu().numpy()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


class JsonLinesPublisher:
    """Write each result as one JSON line to a text stream (stdout by default)."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream if stream is not None else sys.stdout

    def publish(self, record: dict[str, Any]) -> None:
        """Write one line and flush."""
        self.stream.write(json.dumps(record, separators=(",", ":")) + "\n")
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
        data = (json.dumps(record, separators=(",", ":")) + "\n").encode()
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


class OnnxEstimator:
    """The exported contact estimator (ONNX, onnxruntime) as a live-loop estimator.

    Wraps :class:`torchcontact.runtime.EstimatorRuntime` (numpy and onnxruntime only, no torch):
    each call estimates one frame from the joint state and the reading of the loop's single F/T
    sensor. Contact positions and activity come from ``contacts``:

    - ``None``: every slot inactive (no contact; the estimate then explains nothing and the
      forces are zero, while the F/T residual shows any unexplained load);
    - a dict with ``positions (K, 3)`` m in each slot's link frame, ``active (K,)`` and optionally
      ``directions (K, 3)`` (``force_dir`` slots) and ``wrenches (K, 6)`` (``known`` slots);
    - a callable ``contacts(q) -> dict`` as above, called every frame (e.g. from a tactile skin).

    Args:
        path: ``.onnx`` file from ``python -m export estimator`` with exactly one F/T sensor.
        contacts: the contact spec above.
        expect_joint_names: refuse a graph with another joint order (the joint-state sender's).
        intra_op_threads: onnxruntime threads (1: lowest single-frame latency).

    Raises:
        torchcontact.runtime.ModelMismatchError: not an estimator graph or other joints.
        ValueError: a graph with several F/T sensors, or a contact spec of the wrong shape.
    """

    def __init__(
        self,
        path: str,
        contacts: dict[str, Any] | ContactSpec | None = None,
        *,
        expect_joint_names: Sequence[str] | None = None,
        intra_op_threads: int = 1,
    ) -> None:
        import os

        from torchcontact.runtime import EstimatorRuntime

        if not os.path.isfile(path):
            raise ValueError(f"--onnx {path}: no such file")
        self.runtime = EstimatorRuntime(
            path, expect_joint_names=expect_joint_names, intra_op_threads=intra_op_threads
        )
        rt = self.runtime
        if rt.S != 1:
            raise ValueError(
                f"{path} uses sensors {list(rt.sensor_names)}; the live loop reads one F/T sensor:"
                " export with a single --sensor"
            )
        self.contacts = contacts
        self._fixed = None
        if contacts is None:
            self._fixed = {"positions": np.zeros((rt.K, 3)), "active": np.zeros(rt.K)}
        elif not callable(contacts):
            self._fixed = self._check(contacts)

    def _check(self, spec: dict[str, Any]) -> dict[str, Any]:
        K = self.runtime.K
        shapes = {"positions": (K, 3), "active": (K,), "directions": (K, 3), "wrenches": (K, 6)}
        out = {}
        for key, value in spec.items():
            if key not in shapes:
                raise ValueError(f"contact spec key {key!r} not one of {list(shapes)}")
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape != shapes[key]:
                raise ValueError(
                    f"contact spec {key} must have shape {shapes[key]}, got {arr.shape}"
                )
            out[key] = arr
        if "positions" not in out:
            raise ValueError("contact spec needs positions (K, 3)")
        out.setdefault("active", np.ones(K))
        return out

    def __call__(
        self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, ft: np.ndarray
    ) -> dict[str, Any]:
        """Estimate one frame.

        Args:
            q: ``(nv,)`` joint positions in the graph's joint order, rad or m.
            qd: ``(nv,)`` joint velocities.
            qdd: ``(nv,)`` joint accelerations.
            ft: ``(6,)`` reading ``[N; N m]`` in the sensor frame.

        Returns:
            ``force (K, 3)`` N and ``moment (K, 3)`` N m in each slot's link frame,
            ``joint_torques (nv,)``, ``rank``, ``unknowns``, ``residual`` ``(1,)`` and ``status``
            (0: ok), numpy arrays.

        Raises:
            ValueError: no joint state (``q`` empty) or the wrong number of joints.
        """
        nv = self.runtime.nv
        if len(q) != nv:
            raise ValueError(f"joint state has {len(q)} joints, the graph expects {nv}")
        spec = self._fixed if self._fixed is not None else self._check(self.contacts(q))  # type: ignore[misc]
        return self.runtime.step(q, qd, qdd, np.asarray(ft).reshape(1, 6), **spec)


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
    ) -> None:
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
