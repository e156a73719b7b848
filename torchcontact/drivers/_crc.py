"""CRC-16/Modbus (poly 0x8005 reflected as 0xA001, init 0xFFFF, no final xor).

Used by Modbus RTU frames and by the Robotiq FT 300 stream frames. Table-driven, one byte per
step (the reference algorithm of the Modbus over Serial Line specification v1.02, section 6.2.2).
"""

from __future__ import annotations


def _build_table() -> tuple[int, ...]:
    # one entry per byte value: the CRC register after shifting that byte through 8 rounds
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_TABLE = _build_table()


def crc16_modbus(data: bytes | bytearray | memoryview) -> int:
    """Compute the CRC-16/Modbus of ``data``.

    Args:
        data: Bytes to checksum.

    Returns:
        The CRC as an int in ``[0, 0xFFFF]``; on the wire it is sent low byte first.

    Example:
        >>> hex(crc16_modbus(b"123456789"))
        '0x4b37'
    """
    crc = 0xFFFF
    for byte in bytes(data):
        crc = (crc >> 8) ^ _TABLE[(crc ^ byte) & 0xFF]
    return crc


def crc_bytes(data: bytes | bytearray) -> bytes:
    """Return the 2-byte CRC of ``data`` in wire order (low byte first).

    Example:
        >>> crc_bytes(bytes.fromhex("1103006b0003")).hex()  # Modbus spec example
        '7687'
    """
    return crc16_modbus(data).to_bytes(2, "little")


def with_crc(data: bytes | bytearray) -> bytes:
    """Return ``data`` followed by its CRC in wire order, as a Modbus RTU frame."""
    return bytes(data) + crc_bytes(data)


def check_crc(frame: bytes | bytearray | memoryview) -> bool:
    """Whether the last two bytes of ``frame`` are the CRC (low byte first) of the rest."""
    if len(frame) < 3:
        return False
    frame = bytes(frame)
    return crc16_modbus(frame[:-2]) == int.from_bytes(frame[-2:], "little")
