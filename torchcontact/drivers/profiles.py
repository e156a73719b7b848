"""Register-map profiles of Modbus F/T sensors, read from TOML package data.

A profile is a data table (``torchcontact/data/profiles/<name>.toml``) naming the datasheet it
comes from and describing where the six wrench channels live: address, type (int16, uint16,
int32, uint32, float32), word and byte order, scale to SI units per channel, the device id, the
serial settings, an optional zero (tare) command, optional stream mode and identity registers.

Channel order is fixed, [force; moment] = ``fx fy fz mx my mz``, in the sensor frame; the SI
value of a channel is ``raw * scale`` (N for forces, N m for moments).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np

from torchcontact.errors import ProfileError  # noqa: F401  (re-exported)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CHANNELS = ("fx", "fy", "fz", "mx", "my", "mz")
#: Registers per value type.
TYPE_WIDTH = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2}
Order = Literal["big", "little"]


@dataclass(frozen=True)
class Channel:
    """One wrench channel of a register map.

    Attributes:
        name: One of ``fx fy fz mx my mz``.
        address: First holding/input register (0-based protocol address).
        type: ``int16``, ``uint16``, ``int32``, ``uint32`` or ``float32``.
        scale: SI value per raw unit (N or N m per count).
    """

    name: str
    address: int
    type: str
    scale: float

    @property
    def width(self) -> int:
        """Number of 16-bit registers of this channel."""
        return TYPE_WIDTH[self.type]


@dataclass(frozen=True)
class StreamSpec:
    """Stream mode of a sensor (FT 300 style).

    Attributes:
        start_address: Register written with FC16 to start streaming.
        start_value: Value written there.
        rate_hz: Nominal frame rate.
        stop_byte: Byte sent repeatedly to stop the stream.
        stop_seconds: How long to send it.
    """

    start_address: int
    start_value: int
    rate_hz: float
    stop_byte: int = 0xFF
    stop_seconds: float = 0.5


@dataclass(frozen=True)
class Profile:
    """A register-map profile of a Modbus F/T sensor.

    Attributes:
        name: Profile name (file stem).
        description: One line on the device.
        source: The datasheet or driver the table comes from.
        verified: False when the table comes from unofficial sources; see ``note``.
        note: Caveats.
        device_id: Modbus unit id.
        baudrate, parity, bytesize, stopbits: Serial line settings (RTU).
        function: ``holding`` (FC03) or ``input`` (FC04).
        word_order: Order of 16-bit words in 32-bit values.
        byte_order: Order of the two bytes inside each register.
        channels: The six channels, ``fx fy fz mx my mz``.
        zero: Optional ``(address, values)`` FC16 write that zeroes the sensor in hardware.
        stream: Optional stream mode.
        identity: Name -> (address, count) of identity registers.
        extra: Name -> Channel of additional scaled registers (e.g. acceleration).
        noise_std: Datasheet noise standard deviation of the six channels ``[N; N m]``
            (``[noise].std``), or None when the datasheet gives none: the weighted solve of
            ``torchcontact estimate --ft-noise SENSOR=PROFILE`` uses it.
    """

    name: str
    description: str
    source: str
    verified: bool
    note: str
    device_id: int
    baudrate: int
    parity: str
    bytesize: int
    stopbits: int
    function: str
    word_order: Order
    byte_order: Order
    channels: tuple[Channel, ...]
    zero: tuple[int, tuple[int, ...]] | None = None
    stream: StreamSpec | None = None
    identity: dict[str, tuple[int, int]] = field(default_factory=dict)
    extra: dict[str, Channel] = field(default_factory=dict)
    noise_std: tuple[float, ...] | None = None

    @property
    def span(self) -> tuple[int, int]:
        """``(first address, register count)`` covering all six channels in one request."""
        first = min(c.address for c in self.channels)
        last = max(c.address + c.width for c in self.channels)
        return first, last - first

    def decode(self, registers: list[int], first: int | None = None) -> np.ndarray:
        """Decode the wrench from a block of registers read from the device.

        Args:
            registers: Register values (0..65535) starting at address ``first``.
            first: Address of ``registers[0]``; defaults to ``span[0]``.

        Returns:
            (6,) float64 wrench [force; moment] in N and N m, sensor frame.

        Raises:
            ProfileError: If the block does not cover every channel.
        """
        first = self.span[0] if first is None else first
        out = np.empty(6, dtype=np.float64)
        for i, ch in enumerate(self.channels):
            lo = ch.address - first
            if lo < 0 or lo + ch.width > len(registers):
                raise ProfileError(
                    f"profile {self.name!r}: register block at {first} (+{len(registers)}) "
                    f"does not cover channel {ch.name} at {ch.address}"
                )
            out[i] = (
                decode_value(
                    registers[lo : lo + ch.width], ch.type, self.word_order, self.byte_order
                )
                * ch.scale
            )
        return out

    def encode(self, wrench: np.ndarray) -> dict[int, int]:
        """Encode a wrench as the device would hold it (used by the simulator).

        Args:
            wrench: (6,) [force; moment] in N and N m, sensor frame.

        Returns:
            Address -> register value for every channel register; integer types are rounded and
            saturated to their range.
        """
        regs: dict[int, int] = {}
        for value, ch in zip(np.asarray(wrench, dtype=np.float64), self.channels, strict=True):
            words = encode_value(value / ch.scale, ch.type, self.word_order, self.byte_order)
            for k, w in enumerate(words):
                regs[ch.address + k] = w
        return regs


_INT_RANGE = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}


def _datatype(type_: str) -> Any:
    from pymodbus.client.mixin import ModbusClientMixin

    return ModbusClientMixin.DATATYPE[type_.upper()]


def _swap_bytes(words: list[int]) -> list[int]:
    return [((w & 0xFF) << 8) | (w >> 8) for w in words]


def decode_value(words: list[int], type_: str, word_order: Order, byte_order: Order) -> float:
    """Decode one value from its registers with pymodbus' ``convert_from_registers``.

    Args:
        words: The 1 or 2 registers of the value, in the order read from the device.
        type_: ``int16``, ``uint16``, ``int32``, ``uint32`` or ``float32``.
        word_order: ``big`` if the most significant word comes first.
        byte_order: ``big`` if each register holds its most significant byte first (Modbus
            standard); ``little`` for devices that swap bytes inside registers.

    Returns:
        The raw (unscaled) value.

    Example:
        >>> decode_value([0x0000, 0x3FC0], "float32", "little", "big")
        1.5
    """
    from pymodbus.client.mixin import ModbusClientMixin

    if byte_order == "little":
        words = _swap_bytes(list(words))
    value = ModbusClientMixin.convert_from_registers(
        list(words), _datatype(type_), word_order=word_order
    )
    return float(value)  # type: ignore[arg-type]


def encode_value(value: float, type_: str, word_order: Order, byte_order: Order) -> list[int]:
    """Inverse of :func:`decode_value` (rounding and saturating integer types).

    Example:
        >>> encode_value(-2.0, "int32", "big", "little")
        [65535, 65279]
    """
    from pymodbus.client.mixin import ModbusClientMixin

    if type_ in _INT_RANGE:
        lo, hi = _INT_RANGE[type_]
        raw: float | int = int(min(max(round(float(value)), lo), hi))
    else:
        raw = float(np.float32(value))
    words = ModbusClientMixin.convert_to_registers(raw, _datatype(type_), word_order=word_order)
    return _swap_bytes(words) if byte_order == "little" else list(words)


# ---------------------------------------------------------------------------------------------
# loading and validation

_TOP_KEYS = {
    "name", "description", "source", "verified", "note",
    "device", "map", "channels", "zero", "stream", "identity", "extra", "noise",
}  # fmt: skip
_DEVICE_KEYS = {"device_id", "baudrate", "parity", "bytesize", "stopbits"}
_MAP_KEYS = {"function", "word_order", "byte_order"}
_CHANNEL_KEYS = {"name", "address", "type", "scale"}
_STREAM_KEYS = {"start_address", "start_value", "rate_hz", "stop_byte", "stop_seconds"}


def _check_keys(where: str, table: dict[str, Any], allowed: set[str], origin: str) -> None:
    unknown = set(table) - allowed
    if unknown:
        raise ProfileError(
            f"{origin}: unknown key(s) {sorted(unknown)} in {where}; allowed: {sorted(allowed)}"
        )


def _need(table: dict[str, Any], key: str, kind: type | tuple[type, ...], where: str, origin: str):
    if key not in table:
        raise ProfileError(f"{origin}: missing key {key!r} in {where}")
    value = table[key]
    if isinstance(value, bool) and kind is not bool or not isinstance(value, kind):
        raise ProfileError(f"{origin}: {where}.{key} = {value!r} is not a {kind}")
    return value


def _address(value: Any, where: str, origin: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFF:
        raise ProfileError(f"{origin}: {where} = {value!r} is not a register address 0..65535")
    return value


def _channel(t: dict[str, Any], where: str, origin: str) -> Channel:
    _check_keys(where, t, _CHANNEL_KEYS, origin)
    type_ = _need(t, "type", str, where, origin)
    if type_ not in TYPE_WIDTH:
        raise ProfileError(
            f"{origin}: {where}.type = {type_!r}; expected one of {list(TYPE_WIDTH)}"
        )
    scale = float(_need(t, "scale", (int, float), where, origin))
    if scale == 0.0:
        raise ProfileError(f"{origin}: {where}.scale must not be 0")
    return Channel(
        name=_need(t, "name", str, where, origin),
        address=_address(t.get("address"), f"{where}.address", origin),
        type=type_,
        scale=scale,
    )


def parse_profile(data: dict[str, Any], origin: str = "<profile>") -> Profile:
    """Validate a parsed TOML table and build a :class:`Profile`.

    Args:
        data: The table as returned by ``tomllib.loads``.
        origin: File name used in error messages.

    Returns:
        The profile.

    Raises:
        ProfileError: Naming the file and the offending key on any unknown key, missing key, bad
            type, bad order, duplicate or missing channel, or overlapping registers.
    """
    _check_keys("the top level", data, _TOP_KEYS, origin)
    verified = _need(data, "verified", bool, "the top level", origin)
    note = data.get("note", "")
    if not verified and not note:
        raise ProfileError(
            f"{origin}: verified = false needs a 'note' saying where the map is from"
        )
    dev = _need(data, "device", dict, "the top level", origin)
    _check_keys("[device]", dev, _DEVICE_KEYS, origin)
    device_id = _need(dev, "device_id", int, "[device]", origin)
    if not 0 <= device_id <= 247:
        raise ProfileError(f"{origin}: [device].device_id = {device_id} is not in 0..247")
    parity = dev.get("parity", "N")
    if parity not in ("N", "E", "O"):
        raise ProfileError(f"{origin}: [device].parity = {parity!r}; expected N, E or O")
    map_ = data.get("map", {})
    _check_keys("[map]", map_, _MAP_KEYS, origin)
    orders = {}
    for key in ("word_order", "byte_order"):
        orders[key] = map_.get(key, "big")
        if orders[key] not in ("big", "little"):
            raise ProfileError(f"{origin}: [map].{key} = {orders[key]!r}; expected big or little")
    function = map_.get("function", "holding")
    if function not in ("holding", "input"):
        raise ProfileError(f"{origin}: [map].function = {function!r}; expected holding or input")
    raw_channels = _need(data, "channels", list, "the top level", origin)
    channels = [_channel(t, f"[[channels]] #{i}", origin) for i, t in enumerate(raw_channels)]
    names = [c.name for c in channels]
    if sorted(names) != sorted(CHANNELS):
        raise ProfileError(f"{origin}: channels must be exactly {list(CHANNELS)}, got {names}")
    channels.sort(key=lambda c: CHANNELS.index(c.name))
    used: dict[int, str] = {}
    for c in channels:
        for a in range(c.address, c.address + c.width):
            if a in used:
                raise ProfileError(f"{origin}: channels {used[a]} and {c.name} overlap at {a}")
            used[a] = c.name
    span = max(c.address + c.width for c in channels) - min(c.address for c in channels)
    if span > 125:
        raise ProfileError(f"{origin}: channels span {span} registers; one FC03 read allows 125")
    zero = None
    if "zero" in data:
        z = data["zero"]
        _check_keys("[zero]", z, {"address", "values"}, origin)
        values = _need(z, "values", list, "[zero]", origin)
        if not values or not all(isinstance(v, int) and 0 <= v <= 0xFFFF for v in values):
            raise ProfileError(f"{origin}: [zero].values must be a list of uint16, got {values}")
        zero = (_address(z.get("address"), "[zero].address", origin), tuple(values))
    stream = None
    if "stream" in data:
        s = data["stream"]
        _check_keys("[stream]", s, _STREAM_KEYS, origin)
        stream = StreamSpec(
            start_address=_address(s.get("start_address"), "[stream].start_address", origin),
            start_value=_need(s, "start_value", int, "[stream]", origin),
            rate_hz=float(_need(s, "rate_hz", (int, float), "[stream]", origin)),
            stop_byte=int(s.get("stop_byte", 0xFF)),
            stop_seconds=float(s.get("stop_seconds", 0.5)),
        )
    identity = {}
    for key, t in data.get("identity", {}).items():
        _check_keys(f"[identity.{key}]", t, {"address", "count"}, origin)
        count = _need(t, "count", int, f"[identity.{key}]", origin)
        identity[key] = (_address(t.get("address"), f"[identity.{key}].address", origin), count)
    extra = {
        key: _channel({"name": key, **t}, f"[extra.{key}]", origin)
        for key, t in data.get("extra", {}).items()
    }
    noise_std = None
    if "noise" in data:
        nz = _need(data, "noise", dict, "the top level", origin)
        _check_keys("[noise]", nz, {"std", "source"}, origin)
        std = _need(nz, "std", list, "[noise]", origin)
        ok = len(std) == 6 and all(
            isinstance(v, (int, float)) and 0 < v < float("inf") for v in std
        )
        if not ok:
            raise ProfileError(
                f"{origin}: [noise].std must be 6 numbers > 0 [N; N m] (fx fy fz mx my mz), got"
                f" {std}"
            )
        noise_std = tuple(float(v) for v in std)
    return Profile(
        name=_need(data, "name", str, "the top level", origin),
        description=data.get("description", ""),
        source=_need(data, "source", str, "the top level", origin),
        verified=verified,
        note=note,
        device_id=device_id,
        baudrate=int(dev.get("baudrate", 19200)),
        parity=parity,
        bytesize=int(dev.get("bytesize", 8)),
        stopbits=int(dev.get("stopbits", 1)),
        function=function,
        word_order=orders["word_order"],
        byte_order=orders["byte_order"],
        channels=tuple(channels),
        zero=zero,
        stream=stream,
        identity=identity,
        extra=extra,
        noise_std=noise_std,
    )


def available_profiles() -> list[str]:
    """Names of the profiles shipped in ``torchcontact/data/profiles``.

    Example:
        >>> "robotiq-ft300" in available_profiles()
        True
    """
    root = resources.files("torchcontact") / "data" / "profiles"
    return sorted(p.name[: -len(".toml")] for p in root.iterdir() if p.name.endswith(".toml"))


def load_profile(name_or_path: str | Path) -> Profile:
    """Load a shipped profile by name, or any profile file by path.

    Args:
        name_or_path: A shipped profile name (see :func:`available_profiles`) or a ``.toml`` path.

    Returns:
        The validated profile.

    Raises:
        ProfileError: If the profile does not exist or is invalid.

    Example:
        >>> p = load_profile("robotiq-ft300")
        >>> p.device_id, p.span, p.stream.rate_hz
        (9, (180, 6), 100.0)
    """
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise ProfileError(f"profile file {str(path)!r} does not exist")
        text, origin = path.read_text(encoding="utf-8"), str(path)
    else:
        res = resources.files("torchcontact") / "data" / "profiles" / f"{name_or_path}.toml"
        if not res.is_file():
            raise ProfileError(
                f"unknown profile {str(name_or_path)!r}; shipped: {available_profiles()}"
                " (or pass a path to a .toml file)"
            )
        text, origin = res.read_text(encoding="utf-8"), f"{name_or_path}.toml"
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{origin}: not valid TOML: {exc}") from exc
    return parse_profile(data, origin)
