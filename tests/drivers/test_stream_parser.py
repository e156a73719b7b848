"""The FT 300 stream parser: CRC-verified header sync, one-byte slide, no invalid frame out."""

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from torchcontact.drivers._crc import crc16_modbus
from torchcontact.drivers.stream import (
    FRAME_LEN,
    HEADER,
    GapEstimator,
    StreamParser,
    encode_stream_frame,
)

# header-aliasing values: 0x4E20 = 20000 (Fx = 200.00 N) is the header read little-endian;
# 0x2000 followed by 0x004E puts it across the boundary of two values
ALIAS = [20000, 0x2000, 0x004E, -1, 0]
int16 = st.integers(-32768, 32767)
values = st.one_of(int16, st.sampled_from(ALIAS))
frame_values = st.tuples(*[values] * 6)


def valid_windows(data: bytes) -> list[int]:
    """Every offset where a CRC-valid frame starts (the brute-force reference)."""
    return [
        i
        for i in range(len(data) - FRAME_LEN + 1)
        if data[i : i + 2] == HEADER
        and crc16_modbus(data[i : i + 14]) == int.from_bytes(data[i + 14 : i + 16], "little")
    ]


def test_fixture_bytes():
    # hand-checked frame: header, Fx=200.00 N, Fy=-0.01 N, Fz=1.00 N, Mx=0.001, My=-0.002,
    # Mz=0.003 N m (little-endian int16), CRC-16/Modbus low byte first
    frame = encode_stream_frame([20000, -1, 100, 1, -2, 3])
    assert frame[:14] == bytes.fromhex("204e204effff64000100feff0300")
    assert int.from_bytes(frame[14:], "little") == crc16_modbus(frame[:14])
    assert StreamParser().feed(frame) == [(20000, -1, 100, 1, -2, 3)]


def test_aliased_header_is_not_cut():
    # a parser cutting at every header would split after 0x20 0x4E of Fx
    f1 = encode_stream_frame([20000, 20000, 20000, 20000, 20000, 20000])
    p = StreamParser()
    out = p.feed(b"\x20\x4e\x00" + f1 + f1[:5]) + p.feed(f1[5:])
    assert out == [(20000,) * 6] * 2
    assert p.stats.crc_errors >= 1 and p.stats.frames == 2


def test_corrupted_frame_dropped_and_resynced():
    good = [encode_stream_frame([i, 0, 0, 0, 0, i]) for i in range(3)]
    bad = bytearray(good[1])
    bad[7] ^= 0x10
    p = StreamParser()
    assert p.feed(good[0] + bytes(bad) + good[2]) == [(0, 0, 0, 0, 0, 0), (2, 0, 0, 0, 0, 2)]
    assert p.stats.crc_errors == 1 and p.stats.resyncs == 1 and p.stats.bytes_discarded == 16
    assert p.take_discarded() == 0  # consumed by the resync onto frame 2


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.binary(max_size=40), frame_values), max_size=12),
    st.binary(max_size=40),
    st.lists(st.integers(1, 40), min_size=1, max_size=30),
)
def test_recovers_every_valid_frame_and_nothing_else(chunks, tail, cuts):
    stream = b""
    starts, expected = [], []
    for garbage, vals in chunks:
        stream += garbage
        starts.append(len(stream))
        expected.append(tuple(vals))
        stream += encode_stream_frame(vals)
    stream += tail
    # precondition: the only CRC-valid windows are the frames we put there; a garbage window
    # that is a valid frame cannot be told apart from one by any parser (p ~ 2^-32 per byte)
    assume(valid_windows(stream) == starts)
    p = StreamParser()
    out, i, k = [], 0, 0
    while i < len(stream):  # split reads of arbitrary sizes
        n = cuts[k % len(cuts)]
        out += p.feed(stream[i : i + n])
        i, k = i + n, k + 1
    assert out == expected
    assert p.stats.frames == len(expected)
    assert p.stats.bytes_discarded + 16 * len(expected) + p.buffered == len(stream)


@settings(max_examples=100, deadline=None)
@given(st.lists(frame_values, min_size=1, max_size=10), st.integers(0, 15), st.integers(0, 7))
def test_a_corrupted_frame_never_comes_out(frames, byte, bit):
    encoded = [encode_stream_frame(v) for v in frames]
    k = len(frames) // 2
    bad = bytearray(encoded[k])
    bad[byte] ^= 1 << bit
    stream = b"".join(encoded[:k]) + bytes(bad) + b"".join(encoded[k + 1 :])
    expected_starts = [16 * i for i in range(len(frames)) if i != k]
    assume(valid_windows(stream) == expected_starts)
    out = StreamParser().feed(stream)
    assert out == [tuple(v) for i, v in enumerate(frames) if i != k]


def test_gap_estimator_counts_losses_not_jitter():
    period = 10_000_000
    g = GapEstimator(period)
    rng = np.random.default_rng(0)
    sent = [i for i in range(500) if i % 50 != 7]  # every 50th frame lost: 10 losses
    missed = [g.update(int(i * period + rng.uniform(0, 0.8) * period)) for i in sent]
    assert sum(missed) == 10
    assert [m for m in missed if m] == [1] * 10
