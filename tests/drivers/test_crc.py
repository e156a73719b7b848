"""CRC-16/Modbus against published vectors and pymodbus' own implementation."""

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymodbus.framer.rtu import FramerRTU

from torchcontact.drivers._crc import check_crc, crc16_modbus, crc_bytes, with_crc
from torchcontact.drivers.robotiq import fc16_request

# (data, crc) from: the CRC catalogue check value of CRC-16/MODBUS ("123456789" -> 0x4B37);
# Modbus over Serial Line v1.02 / Modicon guide example (11 03 00 6B 00 03 -> CRC bytes 76 87);
# Robotiq FT 300 manual, stream start command 09 10 01 9A 00 01 02 02 00 -> CRC bytes CD CA.
VECTORS = [
    (b"123456789", 0x4B37),
    (bytes.fromhex("1103006B0003"), 0x8776),
    (bytes.fromhex("0910019A0001020200"), 0xCACD),
    (b"", 0xFFFF),
]


@pytest.mark.parametrize(("data", "crc"), VECTORS)
def test_known_vectors(data, crc):
    assert crc16_modbus(data) == crc
    assert crc_bytes(data) == crc.to_bytes(2, "little")


def test_robotiq_stream_start_command_bytes():
    assert fc16_request(9, 410, [0x0200]) == bytes.fromhex("0910019A0001020200CDCA")


@given(st.binary(max_size=300))
def test_matches_pymodbus(data):
    # pymodbus returns the CRC with its bytes swapped: the wire order read as big-endian
    assert FramerRTU.compute_CRC(data) == int.from_bytes(crc_bytes(data), "big")


@given(st.binary(min_size=1, max_size=64), st.integers(0, 7), st.data())
def test_check_detects_single_bit_flips(data, bit, draw):
    frame = bytearray(with_crc(data))
    assert check_crc(frame)
    i = draw.draw(st.integers(0, len(frame) - 1))
    frame[i] ^= 1 << bit
    assert not check_crc(frame)
