"""Robotiq FT 300 / FT 300-S driver: polling (Modbus RTU) and 100 Hz stream mode.

Start-up follows Robotiq's own driver: the sensor may still be streaming from an earlier run and
then answers no Modbus request, so every (re)connect first sends about 0.5 s of 0xFF bytes,
paced at the line rate, and flushes what arrived, before any request. Polling then uses pymodbus'
RTU client; stream mode writes ``0x0200`` to register 410 (FC16) and parses 16-byte frames with
:class:`~torchcontact.drivers.stream.StreamParser`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from torchcontact.drivers._crc import with_crc
from torchcontact.drivers.base import ConnectionLost, FTConnectionError, FTError, SampleFlags
from torchcontact.drivers.modbus import ModbusFTSensor
from torchcontact.drivers.profiles import Profile
from torchcontact.drivers.stream import STREAM_SCALE, GapEstimator, StreamParser


def fc16_request(device_id: int, address: int, values: list[int]) -> bytes:
    """Build a Modbus RTU FC16 (write multiple registers) request frame with its CRC.

    Example:
        >>> fc16_request(9, 410, [0x0200]).hex(" ")  # start the FT 300 stream
        '09 10 01 9a 00 01 02 02 00 cd ca'
    """
    body = bytes([device_id, 0x10]) + address.to_bytes(2, "big") + len(values).to_bytes(2, "big")
    body += bytes([2 * len(values)]) + b"".join(v.to_bytes(2, "big") for v in values)
    return with_crc(body)


class RobotiqFT300(ModbusFTSensor):
    """Robotiq FT 300 over RS-485 (Modbus RTU, 19200 8N1, device id 9).

    Args:
        port: Serial port, e.g. ``/dev/ttyUSB0`` (or a pseudo-terminal of the simulator).
        stream: Use the 100 Hz stream mode instead of polling registers 180-185.
        profile: Register-map profile (default ``robotiq-ft300``).
        timeout: Modbus response timeout, s.
        stop_seconds: Duration of the 0xFF burst sent before any request; default from the
            profile (0.5 s).
        read_identity: Read firmware, serial number and year on connect (into ``identity``).
        name: Sensor name (log column ``ft.<name>``).
        **kwargs: Passed to :class:`~torchcontact.drivers.base.FTSource`.

    Example:
        >>> ft = RobotiqFT300("/dev/ttyUSB0", stream=True)  # doctest: +SKIP
        >>> with ft:  # doctest: +SKIP
        ...     s = ft.read(timeout=0.05)  # FTSample; s.wrench (6,) [N, N, N, N m, N m, N m]
    """

    def __init__(
        self,
        port: str,
        *,
        stream: bool = False,
        profile: str | Profile = "robotiq-ft300",
        timeout: float = 0.05,
        stop_seconds: float | None = None,
        read_identity: bool = True,
        name: str = "ft300",
        **kwargs: Any,
    ) -> None:
        super().__init__(profile, port=port, timeout=timeout, name=name, **kwargs)
        if stream and self.profile.stream is None:
            raise ValueError(f"profile {self.profile.name!r} has no [stream] section")
        self.stream = stream
        spec = self.profile.stream
        self.stop_seconds = (
            stop_seconds if stop_seconds is not None else (spec.stop_seconds if spec else 0.5)
        )
        self.read_identity_on_connect = read_identity
        self.identity: dict[str, Any] = {}
        self.parser = StreamParser()
        rate = spec.rate_hz if spec else 100.0
        self._period_ns = int(round(1e9 / rate))
        self._gap = GapEstimator(self._period_ns)
        self._serial: Any = None
        self._queue: list[tuple[int, np.ndarray, int, SampleFlags]] = []
        self._last_t: int | None = None
        self._after_reconnect = False

    # -- link ------------------------------------------------------------------------------

    def _open_serial(self, timeout: float) -> Any:
        import serial

        try:
            return serial.Serial(
                self.port,
                baudrate=self.profile.baudrate,
                bytesize=self.profile.bytesize,
                parity=self.profile.parity,
                stopbits=self.profile.stopbits,
                timeout=timeout,
                write_timeout=1.0,
            )
        except (serial.SerialException, ValueError) as exc:
            raise FTConnectionError(f"cannot open serial port {self.port!r}: {exc}") from exc

    def send_stop_bytes(self, ser: Any) -> None:
        """Send ``stop_seconds`` of the stop byte at line rate, then flush the input.

        Args:
            ser: An open ``serial.Serial``.
        """
        spec = self.profile.stream
        stop = bytes([spec.stop_byte if spec else 0xFF])
        chunk_s = 0.02
        per_chunk = max(1, int(self.profile.baudrate / 10 * chunk_s))  # 10 bits per byte, 8N1
        end = time.monotonic() + self.stop_seconds
        while time.monotonic() < end:
            ser.write(stop * per_chunk)
            time.sleep(chunk_s)
        ser.flush()
        time.sleep(0.03)  # let the last stream frame in flight arrive, then drop it
        ser.reset_input_buffer()

    def _connect(self) -> None:
        import serial

        if "://" not in str(self.port):
            import os

            if not os.path.exists(str(self.port)):
                raise FTConnectionError(f"serial port {self.port!r} does not exist")
        # stop-bytes-first: a sensor still streaming answers no request
        ser = self._open_serial(timeout=self.timeout)
        try:
            self.send_stop_bytes(ser)
        except (serial.SerialException, OSError) as exc:
            ser.close()
            raise FTConnectionError(f"{self.describe()}: writing stop bytes failed: {exc}") from exc
        if not self.stream:
            ser.close()
            self._open_modbus()
            if self.read_identity_on_connect and not self.identity:
                self.identity = self._identity()
            return
        if self.read_identity_on_connect and not self.identity:
            ser.close()
            self._open_modbus()
            try:
                self.identity = self._identity()
            finally:
                self._close_modbus()
            ser = self._open_serial(timeout=self.timeout)
        spec = self.profile.stream
        assert spec is not None
        ser.write(fc16_request(self.profile.device_id, spec.start_address, [spec.start_value]))
        self._serial = ser
        self.parser.reset()
        self._gap.reset()
        self._queue.clear()
        self._after_reconnect = self._last_t is not None

    def close(self) -> None:
        """Stop the stream (stop bytes) if streaming, then close the port."""
        if self._serial is not None and self._connected:
            try:
                self.send_stop_bytes(self._serial)
            except Exception:  # noqa: BLE001 - the port may already be gone
                pass
        super().close()

    def _disconnect(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except Exception:  # noqa: BLE001 - closing a broken port must not raise
                pass
            self._serial = None
        self._close_modbus()

    def _identity(self) -> dict[str, Any]:
        raw = self.read_identity()
        fw = raw.get("firmware", [])
        fw_bytes = b"".join(w.to_bytes(2, "big") for w in fw)
        serial_number = 0
        for w in raw.get("serial", []):
            serial_number = (serial_number << 16) | w
        return {
            "firmware": fw_bytes.decode("ascii")
            if fw_bytes and all(32 <= b < 127 for b in fw_bytes)
            else ".".join(str(w) for w in fw),
            "serial": serial_number,
            "year": raw.get("year", [0])[0],
            "raw": raw,
        }

    # -- stream ----------------------------------------------------------------------------

    def _receive(self, timeout: float) -> tuple[int, np.ndarray, int, SampleFlags] | None:
        if not self.stream:
            return super()._receive(timeout)
        import serial

        deadline = time.monotonic() + timeout
        while not self._queue:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                self._serial.timeout = left
                n = self._serial.in_waiting
                data = self._serial.read(max(1, n))
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                raise ConnectionLost(f"{self.describe()}: {exc}") from exc
            if data:
                self._ingest(data, time.monotonic_ns())
        return self._queue.pop(0)

    def _ingest(self, data: bytes, t_read: int) -> None:
        before = self.parser.stats.crc_errors
        frames = self.parser.feed(data)
        self.stats.crc_errors += self.parser.stats.crc_errors - before
        self.stats.bytes_discarded = self.parser.stats.bytes_discarded
        m = len(frames)
        for i, raw in enumerate(frames):
            # frames read together were sent one period apart: back-date all but the last
            t = t_read - (m - 1 - i) * self._period_ns
            if self._last_t is not None:
                t = max(t, self._last_t + 1)
            discarded = self.parser.take_discarded()
            flags = SampleFlags.STREAM
            if self._after_reconnect and self._last_t is not None:
                # frames the sensor sent while the link was down
                missed = max(0, int(round((t - self._last_t) / self._period_ns)) - 1)
                self._gap.update(t)
                self._after_reconnect = False
            else:
                missed = max(self._gap.update(t), discarded // 16)
            self._last_t = t
            wrench = np.asarray(raw, dtype=np.float64) * STREAM_SCALE
            self._queue.append((t, wrench, missed, flags))

    def read_registers(self, address: int, count: int) -> list[int] | None:
        """Read registers (polling mode or before streaming starts; see the base class).

        Raises:
            FTError: While streaming (the sensor answers no request then).
        """
        if self._serial is not None:
            raise FTError(f"{self.describe()}: no Modbus request while streaming")
        return super().read_registers(address, count)
