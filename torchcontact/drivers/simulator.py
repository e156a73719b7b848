"""Simulated Modbus F/T sensors that speak the device's exact bytes, with fault injection.

* :class:`RtuSimulator` serves a profile over a pseudo-terminal (``os.openpty``), building every
  Modbus RTU response by hand (FC03, FC16 only, exception responses, CRC-16/Modbus) and, for
  profiles with a ``[stream]`` section (FT 300), the 100 Hz stream: an FC16 write of the start
  value to the start register is echoed and starts the stream; about 0.5 s of 0xFF stops it.
  A stable symlink names the port, so a simulated unplug (the pty closes and a new one appears
  under the same name) looks like a USB adapter being re-plugged.
* :class:`TcpSimulator` serves the same registers through a pymodbus ``ModbusTcpServer`` on
  127.0.0.1, with delays, refused requests and dropped connections.

Faults are drawn from a seeded generator, so a test run is reproducible, and every fault is
counted in :attr:`SimStats` so tests can compare what was lost with what the driver reports.
"""

from __future__ import annotations

import asyncio
import os
import select
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.drivers._crc import check_crc, with_crc
from torchcontact.drivers.profiles import Profile, load_profile
from torchcontact.drivers.stream import encode_stream_frame, wrench_to_counts

#: A wrench signal: monotonic time since start (s) -> (6,) [force; moment] N, N m.
Signal = Callable[[float], np.ndarray]


def sine_signal(
    offset: tuple[float, ...] = (1.0, -2.0, 15.0, 0.1, -0.05, 0.02),
    amplitude: tuple[float, ...] = (10.0, 5.0, 20.0, 0.5, 0.3, 0.2),
    freq_hz: tuple[float, ...] = (0.5, 0.7, 0.3, 1.1, 0.9, 1.3),
) -> Signal:
    """Synthetic wrench: one sinusoid per channel.

    Args:
        offset: (6,) mean [force; moment], N and N m.
        amplitude: (6,) amplitudes, N and N m.
        freq_hz: (6,) frequencies, Hz.

    Returns:
        A :data:`Signal`.

    Example:
        >>> sine_signal()(0.0)[:3]
        array([ 1., -2., 15.])
    """
    o, a, f = (np.asarray(v, dtype=np.float64) for v in (offset, amplitude, freq_hz))

    def signal(t: float) -> np.ndarray:
        return o + a * np.sin(2.0 * np.pi * f * t)

    return signal


def constant_signal(wrench: np.ndarray | list[float]) -> Signal:
    """A constant wrench (6,) [force; moment], N and N m."""
    value = np.asarray(wrench, dtype=np.float64).reshape(6)
    return lambda t: value.copy()


def frame_pattern_signal(rate_hz: float = 100.0) -> Signal:
    """A pattern that makes every frame distinct and aliases the stream header.

    Fx = Fz = 200.00 N (encoded 0x4E20, i.e. the bytes 0x20 0x4E of the header), Fy ramps by
    1 N per frame period over 300 values, Mx cycles over 7 values; used to check that frames
    arrive in order, once, and intact.

    Example:
        >>> frame_pattern_signal()(0.01)[:3]
        array([ 200., -149.,  200.])
    """

    def signal(t: float) -> np.ndarray:
        k = round(t * rate_hz)
        return np.array([200.0, (k % 300) - 150.0, 200.0, 0.001 * (k % 7), -0.5, 0.25])

    return signal


def parquet_signal(path: str | Path, sensor: str | None = None) -> Signal:
    """Replay the column ``ft.<sensor>`` of a Parquet log (looping, at its recorded timing).

    Args:
        path: Log file with ``t_ns`` (int64) and ``ft.<sensor>`` (6 floats per row).
        sensor: Sensor name; default the first ``ft.*`` column.

    Returns:
        A :data:`Signal` holding the last recorded value at each time.

    Raises:
        ValueError: If the column is missing or empty, naming the columns present.
    """
    from torchcontact.logs.format import open_log

    table = open_log(path).read()  # the one Parquet reader (checksums verified)
    cols = [c for c in table.column_names if c.startswith("ft.")]
    col = f"ft.{sensor}" if sensor else (cols[0] if cols else None)
    if col is None or col not in table.column_names:
        raise ValueError(f"{path}: no column {col or 'ft.*'}; columns: {table.column_names}")
    values = np.asarray(table.column(col).to_pylist(), dtype=np.float64).reshape(-1, 6)
    if len(values) == 0:
        raise ValueError(f"{path}: column {col} is empty")
    if "t_ns" in table.column_names:
        t = np.asarray(table.column("t_ns").to_numpy(), dtype=np.int64)
        t_s = (t - t[0]) / 1e9
    else:
        t_s = np.arange(len(values)) / 100.0
    period = float(t_s[-1]) + (float(np.median(np.diff(t_s))) if len(t_s) > 1 else 0.01)

    def signal(now: float) -> np.ndarray:
        i = int(np.searchsorted(t_s, now % period, side="right")) - 1
        return values[max(i, 0)].copy()

    return signal


@dataclass
class Faults:
    """Fault injection settings (rates are probabilities per frame or response).

    Attributes:
        drop: Stream frame not sent / request not answered.
        corrupt: One byte of a stream frame or response flipped (bad CRC).
        split: Bytes written in 2-4 pieces with short pauses.
        delay_s: Extra delay before each response and random stream jitter up to this, s.
        disconnect_every_s: Unplug the port (pty closed and re-created; TCP clients dropped)
            this often, s; 0 disables.
        disconnect_s: How long the port stays away, s.
        streaming_at_start: The sensor is already streaming when the simulator starts.
        seed: Random seed.
    """

    drop: float = 0.0
    corrupt: float = 0.0
    split: float = 0.0
    delay_s: float = 0.0
    disconnect_every_s: float = 0.0
    disconnect_s: float = 0.3
    streaming_at_start: bool = False
    seed: int = 0


@dataclass
class SimStats:
    """What the simulator did (to compare with what the driver reports)."""

    requests: int = 0
    responses: int = 0
    exceptions: int = 0
    frames_sent: int = 0
    frames_dropped: int = 0
    frames_corrupted: int = 0
    stream_starts: int = 0
    stream_stops: int = 0
    disconnects: int = 0
    frame_slots: int = 0
    sent_wrenches: list[np.ndarray] = field(default_factory=list, repr=False)
    sent_slots: list[int] = field(default_factory=list, repr=False)

    def as_dict(self) -> dict[str, int]:
        """Counters as a dict (without the recorded wrenches)."""
        d = asdict(self)
        d.pop("sent_wrenches")
        d.pop("sent_slots")
        return d


def _default_identity() -> dict[int, int]:
    regs = {}
    for i, w in enumerate(np.frombuffer(b"V1.0.4", dtype=">u2").tolist()):
        regs[500 + i] = w
    for i, w in enumerate([0x0000, 0x0000, 0x0001, 0xE240]):  # serial number 123456
        regs[510 + i] = w
    regs[514] = 2019
    return regs


class RegisterMap:
    """The device's holding registers, channels computed from the signal at read time."""

    def __init__(self, profile: Profile, signal: Signal, t0: float) -> None:
        self.profile = profile
        self.signal = signal
        self.t0 = t0
        self.static: dict[int, int] = {}
        if profile.identity:
            self.static.update(_default_identity())
        for ch in profile.extra.values():  # FT 300 acceleration: 1 g along -z
            from torchcontact.drivers.profiles import encode_value

            value = -1.0 if ch.name.endswith("z") else 0.0
            words = encode_value(value / ch.scale, ch.type, profile.word_order, profile.byte_order)
            for k, w in enumerate(words):
                self.static[ch.address + k] = w
        if profile.stream:
            self.static[profile.stream.start_address] = 0
        if profile.zero:
            self.static[profile.zero[0]] = 0
        self.bias = np.zeros(6)
        self.channel_addresses = set(profile.encode(np.zeros(6)))

    def wrench(self, now: float) -> np.ndarray:
        """The signal at ``now`` (monotonic s) minus any hardware zero."""
        return np.asarray(self.signal(now - self.t0), dtype=np.float64) - self.bias

    def read(self, address: int, count: int, now: float) -> list[int] | None:
        """Registers ``address..address+count``; ``None`` if any is not mapped."""
        live = self.profile.encode(self.wrench(now))
        out = []
        for a in range(address, address + count):
            if a in live:
                out.append(live[a])
            elif a in self.static:
                out.append(self.static[a])
            else:
                return None
        return out

    def writable(self, address: int, count: int) -> bool:
        """Whether every register in the range may be written."""
        allowed = set()
        if self.profile.stream:
            allowed.add(self.profile.stream.start_address)
        if self.profile.zero:
            allowed.update(range(self.profile.zero[0], self.profile.zero[0] + 1))
        return all(a in allowed for a in range(address, address + count))


class RtuSimulator:
    """A Modbus RTU F/T sensor on a pseudo-terminal, byte-exact, stream mode included.

    Args:
        profile: Profile name, path or object (default the FT 300).
        signal: Wrench signal; default :func:`sine_signal`.
        faults: Fault injection; default none.
        link: Stable path of the port (a symlink to the current pty); default a new temp path.
        record: Keep the counts and slot (period index) of every stream frame sent intact
            (``stats.sent_wrenches``, ``stats.sent_slots``).
        line_rate: Pace responses as the serial line would (10 bits per byte at the profile's
            baud rate, plus the 3.5-character RTU silence); a pty itself is instantaneous.

    Example:
        >>> with RtuSimulator() as sim:  # doctest: +SKIP
        ...     ft = RobotiqFT300(sim.port, stream=True)
    """

    def __init__(
        self,
        profile: str | Profile = "robotiq-ft300",
        signal: Signal | None = None,
        faults: Faults | None = None,
        link: str | Path | None = None,
        record: bool = False,
        line_rate: bool = True,
    ) -> None:
        self.profile = profile if isinstance(profile, Profile) else load_profile(profile)
        self.faults = faults or Faults()
        self.rng = np.random.default_rng(self.faults.seed)
        self.stats = SimStats()
        self.record = record
        self.line_rate = line_rate
        self.t0 = time.monotonic()
        self.registers = RegisterMap(self.profile, signal or sine_signal(), self.t0)
        if link is None:
            self._tmp = tempfile.mkdtemp(prefix="torchcontact-sim-")
            link = Path(self._tmp) / f"{self.profile.name}.pty"
        self.link = Path(link)
        self.streaming = self.faults.streaming_at_start and self.profile.stream is not None
        self._master = self._slave = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._rx = bytearray()
        self._ff_run_start: float | None = None
        self._ff_run_len = 0
        self._lock = threading.Lock()

    @property
    def port(self) -> str:
        """Path to open with pyserial or pymodbus (a symlink to the current pty slave)."""
        return str(self.link)

    # -- pty management --------------------------------------------------------------------

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        # keep our own slave fd open: the master then never sees EIO when a client closes
        self._master, self._slave = master, slave
        tmp = self.link.with_name(self.link.name + ".new")
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.link)

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def start(self) -> RtuSimulator:
        """Create the pty and start serving in a background thread."""
        self._open_pty()
        self._thread = threading.Thread(target=self._run, name="rtu-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving, close the pty and remove the link."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close_pty()
        if self.link.is_symlink():
            self.link.unlink()

    def __enter__(self) -> RtuSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- output with faults ----------------------------------------------------------------

    def _write(self, data: bytes) -> None:
        if self._master < 0:
            return
        pieces = [data]
        if self.faults.split and self.rng.random() < self.faults.split and len(data) > 1:
            k = int(self.rng.integers(2, min(4, len(data)) + 1))
            cuts = sorted(self.rng.choice(np.arange(1, len(data)), size=k - 1, replace=False))
            pieces = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]
        for i, piece in enumerate(pieces):
            if i:
                time.sleep(0.001)
            try:
                os.write(self._master, piece)
            except OSError:
                return

    def _corrupt(self, data: bytes) -> bytes:
        if self.faults.corrupt and self.rng.random() < self.faults.corrupt:
            b = bytearray(data)
            i = int(self.rng.integers(0, len(b)))
            b[i] ^= 1 << int(self.rng.integers(0, 8))
            return bytes(b)
        return data

    # -- Modbus RTU slave ------------------------------------------------------------------

    def _exception(self, fc: int, code: int) -> bytes:
        self.stats.exceptions += 1
        return with_crc(bytes([self.profile.device_id, fc | 0x80, code]))

    def _handle_request(self, frame: bytes, now: float) -> bytes | None:
        dev, fc = frame[0], frame[1]
        self.stats.requests += 1
        if fc == 0x03:
            address = int.from_bytes(frame[2:4], "big")
            count = int.from_bytes(frame[4:6], "big")
            if not 1 <= count <= 125:
                return self._exception(fc, 0x03)
            regs = self.registers.read(address, count, now)
            if regs is None:
                return self._exception(fc, 0x02)
            body = bytes([dev, fc, 2 * count]) + b"".join(r.to_bytes(2, "big") for r in regs)
            return with_crc(body)
        if fc == 0x10:
            address = int.from_bytes(frame[2:4], "big")
            count = int.from_bytes(frame[4:6], "big")
            values = [int.from_bytes(frame[7 + 2 * i : 9 + 2 * i], "big") for i in range(count)]
            if not self.registers.writable(address, count):
                return self._exception(fc, 0x02)
            spec, zero = self.profile.stream, self.profile.zero
            if spec and address == spec.start_address and values[0] == spec.start_value:
                self.streaming = True
                self.stats.stream_starts += 1
                self._next_frame = now + 1.0 / spec.rate_hz
            elif zero and address == zero[0] and tuple(values) == zero[1]:
                self.registers.bias = self.registers.wrench(now) + self.registers.bias
            return with_crc(frame[:6])
        return self._exception(fc, 0x01)  # only FC03 and FC16 are implemented, as on the FT 300

    def _request_length(self) -> int | None:
        """Length of the request at the start of the buffer, or None if not yet known."""
        rx = self._rx
        if len(rx) < 2:
            return None
        fc = rx[1]
        if fc == 0x10:
            return 9 + rx[6] if len(rx) >= 7 else None
        return 8  # FC03 and every unsupported FC of the same shape

    def _serve_requests(self, now: float) -> None:
        while True:
            rx = self._rx
            # a slave skips bytes that cannot start a frame addressed to it (line noise, 0xFF)
            while rx and rx[0] != self.profile.device_id:
                del rx[0]
            n = self._request_length()
            if n is None or len(rx) < n:
                return
            frame = bytes(rx[:n])
            if not check_crc(frame):
                del rx[0]
                continue
            del rx[:n]
            reply = self._handle_request(frame, now)
            if reply is None:
                continue
            if self.faults.drop and self.rng.random() < self.faults.drop:
                continue
            delay = self.faults.delay_s
            if self.line_rate:  # transmission of request and reply, plus 3.5 chars of silence
                delay += (len(frame) + len(reply) + 3.5) * 10.0 / self.profile.baudrate
            if delay:
                time.sleep(delay)
            self._write(self._corrupt(reply))
            self.stats.responses += 1
            if self.streaming:
                self._rx.clear()
                return

    def _watch_stop_bytes(self, data: bytes, now: float) -> None:
        spec = self.profile.stream
        assert spec is not None
        for b in data:
            if b == spec.stop_byte:
                if self._ff_run_start is None:
                    self._ff_run_start = now
                self._ff_run_len += 1
            else:
                self._ff_run_start, self._ff_run_len = None, 0
        if self._ff_run_start is None:
            return
        # about stop_seconds of 0xFF at line rate, by time or by byte count
        need_bytes = 0.8 * spec.stop_seconds * self.profile.baudrate / 10
        if now - self._ff_run_start >= 0.8 * spec.stop_seconds or self._ff_run_len >= need_bytes:
            self.streaming = False
            self.stats.stream_stops += 1
            self._ff_run_start, self._ff_run_len = None, 0
            self._rx.clear()

    def _send_frame(self, now: float) -> None:
        wrench = self.registers.wrench(now)
        frame = encode_stream_frame(wrench_to_counts(wrench))
        slot = self.stats.frame_slots  # one slot per period, whatever happens to the frame
        self.stats.frame_slots += 1
        if self.faults.drop and self.rng.random() < self.faults.drop:
            self.stats.frames_dropped += 1
            return
        out = self._corrupt(frame)
        if out != frame:
            self.stats.frames_corrupted += 1
        else:
            self.stats.frames_sent += 1
            if self.record:
                self.stats.sent_wrenches.append(wrench_to_counts(wrench))
                self.stats.sent_slots.append(slot)
        self._write(out)

    def _unplug(self) -> None:
        self.stats.disconnects += 1
        self._close_pty()
        self.streaming = False
        self._rx.clear()
        self._stop.wait(self.faults.disconnect_s)
        if not self._stop.is_set():
            self._open_pty()

    def _run(self) -> None:
        spec = self.profile.stream
        period = 1.0 / spec.rate_hz if spec else 0.01
        self._next_frame = time.monotonic() + period
        next_unplug = (
            time.monotonic() + self.faults.disconnect_every_s
            if self.faults.disconnect_every_s
            else float("inf")
        )
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_unplug:
                self._unplug()
                next_unplug = time.monotonic() + self.faults.disconnect_every_s
                continue
            wait = max(0.0, self._next_frame - now) if self.streaming else 0.02
            try:
                ready, _, _ = select.select([self._master], [], [], min(wait, 0.02))
                data = os.read(self._master, 4096) if ready else b""
            except OSError:
                data = b""
            now = time.monotonic()
            if data:
                if self.streaming:
                    self._watch_stop_bytes(data, now)
                else:
                    self._rx += data
                    self._serve_requests(now)
            if self.streaming and now >= self._next_frame:
                jitter = (
                    self.faults.delay_s * float(self.rng.random()) if self.faults.delay_s else 0
                )
                if jitter:
                    time.sleep(jitter)
                # the sensor samples on its own clock: evaluate the signal at the frame's slot
                self._send_frame(self._next_frame)
                self._next_frame += period
                if now - self._next_frame > 10 * period:  # fell far behind: do not burst
                    self._next_frame = now + period


class TcpSimulator:
    """A Modbus TCP F/T sensor: a pymodbus ``ModbusTcpServer`` on 127.0.0.1.

    Registers are pymodbus ``SimData`` blocks; an async ``action`` refreshes the channel
    registers from the signal on every read and injects delays, refusals (``drop``: answered
    with a DEVICE_BUSY exception) and dropped connections.

    Args:
        profile: Profile name, path or object.
        signal: Wrench signal; default :func:`sine_signal`.
        faults: Fault injection.
        host: Address to bind; loopback by default.
        port: TCP port; 0 picks a free one (see :attr:`port` after :meth:`start`).
    """

    def __init__(
        self,
        profile: str | Profile = "robotiq-ft300",
        signal: Signal | None = None,
        faults: Faults | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
    ) -> None:
        self.profile = profile if isinstance(profile, Profile) else load_profile(profile)
        self.faults = faults or Faults()
        self.rng = np.random.default_rng(self.faults.seed)
        self.stats = SimStats()
        self.t0 = time.monotonic()
        self.registers = RegisterMap(self.profile, signal or sine_signal(), self.t0)
        self.host, self.port = host, port
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    def _device(self) -> Any:
        from pymodbus.simulator import DataType, SimData, SimDevice

        regs = {**self.registers.static, **self.profile.encode(np.zeros(6))}
        blocks = [
            SimData(address=a, values=v, datatype=DataType.REGISTERS)
            for a, v in sorted(regs.items())
        ]
        return SimDevice(id=self.profile.device_id, simdata=blocks, action=self._action)

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> Any:
        from pymodbus.constants import ExcCodes

        self.stats.requests += 1
        if self.faults.delay_s:
            await asyncio.sleep(self.faults.delay_s)
        if self.faults.drop and self.rng.random() < self.faults.drop:
            self.stats.exceptions += 1
            return ExcCodes.DEVICE_BUSY
        now = time.monotonic()
        if set_values is not None:
            zero = self.profile.zero
            if zero and address == zero[0] and tuple(set_values) == zero[1]:
                self.registers.bias = self.registers.wrench(now) + self.registers.bias
        for a, v in self.profile.encode(self.registers.wrench(now)).items():
            current_registers[a - start_address] = v
        self.stats.responses += 1
        return None

    async def _serve(self) -> None:
        from pymodbus.server import ModbusTcpServer

        self._server = ModbusTcpServer(self._device(), address=(self.host, self.port))
        await self._server.listen()
        self.port = self._server.transport.sockets[0].getsockname()[1]
        self._ready.set()
        every = self.faults.disconnect_every_s
        while True:
            await asyncio.sleep(every if every else 3600)
            if every:
                self.drop_connections()

    def drop_connections(self) -> None:
        """Close every client connection (the server keeps listening)."""
        if self._server is None:
            return
        for conn in list(self._server.active_connections.values()):
            conn.close()
        self.stats.disconnects += 1

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        try:
            self._loop.run_until_complete(self._serve())
        except asyncio.CancelledError:
            pass
        except BaseException as exc:  # noqa: BLE001 - reported by start()
            self._error = exc
            self._ready.set()
        finally:
            self._loop.close()

    def start(self) -> TcpSimulator:
        """Start the server in a background thread and wait until it listens.

        Raises:
            OSError: If the address cannot be bound.
        """
        self._thread = threading.Thread(target=self._run, name="tcp-sim", daemon=True)
        self._thread.start()
        self._ready.wait(5.0)
        if self._error is not None:
            raise OSError(f"cannot serve Modbus TCP on {self.host}:{self.port}: {self._error}")
        return self

    def stop(self) -> None:
        """Shut the server down."""
        loop = self._loop
        if loop is not None and self._server is not None and loop.is_running():

            async def _shutdown() -> None:
                await self._server.shutdown()
                for task in asyncio.all_tasks():
                    if task is not asyncio.current_task():
                        task.cancel()

            fut = asyncio.run_coroutine_threadsafe(_shutdown(), loop)
            try:
                fut.result(2.0)
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass
        if self._thread is not None:
            self._thread.join(2.0)

    def __enter__(self) -> TcpSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
