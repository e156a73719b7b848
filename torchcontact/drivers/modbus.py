"""A generic Modbus F/T sensor (RTU or TCP) described by a register-map profile.

Polls the six channels with one FC03 (or FC04) request per sample through pymodbus' synchronous
clients, with a short timeout and no retries: a control loop rather loses one sample than
stalls for the pymodbus defaults (3 s x 3 retries).
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

import numpy as np

from torchcontact.drivers.base import (
    ConnectionLost,
    FTConnectionError,
    FTError,
    FTSource,
    SampleFlags,
)
from torchcontact.drivers.profiles import Profile, load_profile


def parse_hostport(text: str, default_port: int = 502, allow_zero: bool = False) -> tuple[str, int]:
    """Split ``host:port`` (``port`` optional; 0 = any free port when ``allow_zero``).

    Raises:
        ValueError: If the port is not an integer in 1..65535.

    Example:
        >>> parse_hostport("127.0.0.1:1502")
        ('127.0.0.1', 1502)
    """
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, str(default_port)
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not (0 if allow_zero else 1) <= number <= 65535 or not host:
        raise ValueError(f"expected HOST:PORT with PORT in 1..65535, got {text!r}")
    return host, number


def quiet_pymodbus(level: int = logging.CRITICAL) -> None:
    """Silence pymodbus' own logging (it logs every timeout at ERROR level)."""
    logging.getLogger("pymodbus").setLevel(level)
    for name in ("pymodbus.logging",):
        logging.getLogger(name).setLevel(level)


class ModbusFTSensor(FTSource):
    """Poll a Modbus F/T sensor described by a :class:`~torchcontact.drivers.profiles.Profile`.

    Exactly one of ``port`` (RTU over a serial port) or ``host`` (Modbus TCP) is given.

    Args:
        profile: Profile name, path, or object.
        port: Serial port (``/dev/ttyUSB0``), Modbus RTU with the profile's line settings.
        host: Modbus TCP host.
        tcp_port: Modbus TCP port.
        timeout: Response timeout per request, s.
        name: Sensor name (log column ``ft.<name>``); defaults to the profile name.
        **kwargs: Passed to :class:`~torchcontact.drivers.base.FTSource` (backoff settings).

    Raises:
        ValueError: If neither or both of ``port`` and ``host`` are given.
    """

    def __init__(
        self,
        profile: str | Profile,
        *,
        port: str | None = None,
        host: str | None = None,
        tcp_port: int = 502,
        timeout: float = 0.1,
        name: str | None = None,
        **kwargs: Any,
    ) -> None:
        self.profile = profile if isinstance(profile, Profile) else load_profile(profile)
        if (port is None) == (host is None):
            raise ValueError("give exactly one of port= (Modbus RTU) or host= (Modbus TCP)")
        super().__init__(name or self.profile.name.replace("-", "_"), **kwargs)
        self.port, self.host, self.tcp_port = port, host, tcp_port
        self.timeout = float(timeout)
        self._client: Any = None
        self._first, self._count = self.profile.span
        self.modbus_errors = 0

    def describe(self) -> str:
        """Identify the sensor by profile and port or host."""
        where = self.port if self.port is not None else f"{self.host}:{self.tcp_port}"
        return f"{self.profile.name} at {where}"

    # -- link ------------------------------------------------------------------------------

    def _open_modbus(self) -> None:
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        if self.port is not None:
            if "://" not in self.port and not os.path.exists(self.port):
                raise FTConnectionError(f"serial port {self.port!r} does not exist")
            client = ModbusSerialClient(
                self.port,
                baudrate=self.profile.baudrate,
                bytesize=self.profile.bytesize,
                parity=self.profile.parity,
                stopbits=self.profile.stopbits,
                timeout=self.timeout,
                retries=0,
            )
        else:
            client = ModbusTcpClient(self.host, port=self.tcp_port, timeout=self.timeout, retries=0)
        if not client.connect():
            client.close()
            raise FTConnectionError(f"cannot connect to {self.describe()}")
        self._client = client

    def _close_modbus(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            except Exception:  # noqa: BLE001 - closing a broken link must not raise
                pass
            self._client = None

    def _connect(self) -> None:
        self._open_modbus()

    def _disconnect(self) -> None:
        self._close_modbus()

    # -- requests --------------------------------------------------------------------------

    def read_registers(self, address: int, count: int) -> list[int] | None:
        """Read ``count`` registers at ``address`` with the profile's function code.

        Returns:
            The registers, or ``None`` on timeout or a Modbus exception response.

        Raises:
            ConnectionLost: If the link is closed or broke.
        """
        from pymodbus.exceptions import ConnectionException, ModbusIOException

        if self._client is None:
            raise ConnectionLost(f"{self.describe()}: not connected")
        read = (
            self._client.read_holding_registers
            if self.profile.function == "holding"
            else self._client.read_input_registers
        )
        try:
            rr = read(address, count=count, device_id=self.profile.device_id)
        except ConnectionException as exc:
            raise ConnectionLost(str(exc)) from exc
        except ModbusIOException as exc:
            if "CLOSING" in str(exc) or not self._client.connected:
                raise ConnectionLost(str(exc)) from exc
            return None
        if rr.isError() or len(getattr(rr, "registers", ())) != count:
            self.modbus_errors += 1
            return None
        return list(rr.registers)

    def write_registers(self, address: int, values: list[int]) -> None:
        """Write registers with FC16.

        Raises:
            FTError: On timeout or an exception response.
        """
        from pymodbus.exceptions import ModbusException

        if self._client is None:
            raise FTError(f"{self.describe()}: not connected")
        try:
            rr = self._client.write_registers(address, values, device_id=self.profile.device_id)
        except ModbusException as exc:
            raise FTError(f"{self.describe()}: write to {address} failed: {exc}") from exc
        if rr.isError():
            raise FTError(f"{self.describe()}: write to {address} refused: {rr}")

    def _receive(self, timeout: float) -> tuple[int, np.ndarray, int, SampleFlags] | None:
        regs = self.read_registers(self._first, self._count)
        if regs is None:
            return None
        return time.monotonic_ns(), self.profile.decode(regs, self._first), 0, SampleFlags.NONE

    def zero(self) -> None:
        """Zero the sensor in hardware with the profile's zero command.

        Raises:
            FTError: If the profile has no zero command (use :meth:`tare`) or the write fails.
        """
        if self.profile.zero is None:
            raise FTError(f"profile {self.profile.name!r} has no zero command; use tare()")
        address, values = self.profile.zero
        self.write_registers(address, list(values))

    def read_identity(self) -> dict[str, list[int]]:
        """Read the profile's identity registers raw.

        Returns:
            Name -> register values.

        Raises:
            FTError: If a read times out.
        """
        out = {}
        for key, (address, count) in self.profile.identity.items():
            regs = self.read_registers(address, count)
            if regs is None:
                raise FTError(f"{self.describe()}: no answer reading identity {key!r}")
            out[key] = regs
        return out

    def read_extra(self) -> dict[str, float]:
        """Read the profile's extra channels (e.g. FT 300 acceleration, g), scaled.

        Returns:
            Name -> value; channels that timed out are missing.
        """
        from torchcontact.drivers.profiles import decode_value

        out = {}
        p = self.profile
        for key, ch in p.extra.items():
            regs = self.read_registers(ch.address, ch.width)
            if regs is not None:
                out[key] = decode_value(regs, ch.type, p.word_order, p.byte_order) * ch.scale
        return out
