"""Robotiq FT 300 stream-mode frames: encoding and a CRC-synchronised parser.

Frame layout (Robotiq FT 300 / FT 300-S instruction manual, "Data stream"; also Robotiq's
``rq_sensor_com.c``), 16 bytes sent at 100 Hz after ``0x0200`` is written to register 410::

    offset  size  content
    0       2     header 0x20 0x4E
    2       12    Fx Fy Fz Mx My Mz, little-endian int16; F in 1/100 N, M in 1/1000 N m
    14      2     CRC-16/Modbus of bytes 0..13, low byte first

The header is not unique: Fx = 200.00 N encodes as ``0x20 0x4E`` too. A header is therefore only
trusted when the CRC of the 16 bytes starting there matches; otherwise the parser slides one byte
and searches again, so a frame is never cut at an aliased header.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchcontact.drivers._crc import crc16_modbus

#: Stream frame header bytes.
HEADER = b"\x20\x4e"
#: Length of one stream frame in bytes.
FRAME_LEN = 16
#: Raw count to SI unit factor per channel [Fx, Fy, Fz, Mx, My, Mz] (N, N m).
STREAM_SCALE = np.array([0.01, 0.01, 0.01, 0.001, 0.001, 0.001], dtype=np.float64)


def encode_stream_frame(raw: np.ndarray | list[int] | tuple[int, ...]) -> bytes:
    """Encode six raw int16 counts as one 16-byte stream frame with its CRC.

    Args:
        raw: (6,) int counts [Fx, Fy, Fz, Mx, My, Mz] in the sensor's units (1/100 N, 1/1000 N m),
            each in ``[-32768, 32767]``.

    Returns:
        The 16 bytes as sent by the sensor.

    Raises:
        ValueError: If ``raw`` has not 6 entries or a value does not fit in int16.

    Example:
        >>> encode_stream_frame([20000, 0, 0, 0, 0, 0])[:4].hex()  # Fx = 200.00 N: header alias
        '204e204e'
    """
    values = [int(v) for v in np.asarray(raw).reshape(-1)]
    if len(values) != 6:
        raise ValueError(f"a stream frame carries 6 values, got {len(values)}")
    if any(not -32768 <= v <= 32767 for v in values):
        raise ValueError(f"stream values must fit in int16, got {values}")
    body = HEADER + np.asarray(values, dtype="<i2").tobytes()
    return body + crc16_modbus(body).to_bytes(2, "little")


def wrench_to_counts(wrench: np.ndarray) -> np.ndarray:
    """Quantise a wrench to FT 300 counts, saturating at the int16 range.

    Args:
        wrench: (6,) [force; moment] in N and N m, sensor frame.

    Returns:
        (6,) int64 counts (1/100 N, 1/1000 N m).
    """
    counts = np.rint(np.asarray(wrench, dtype=np.float64) / STREAM_SCALE)
    return np.clip(counts, -32768, 32767).astype(np.int64)


@dataclass
class StreamParserStats:
    """Counters of a :class:`StreamParser`.

    Attributes:
        frames: Valid frames emitted.
        crc_errors: Header candidates whose 16-byte window failed the CRC.
        resyncs: Valid frames that were found only after discarding bytes (loss of sync).
        bytes_discarded: Bytes dropped while searching for a valid frame.
    """

    frames: int = 0
    crc_errors: int = 0
    resyncs: int = 0
    bytes_discarded: int = 0


class StreamParser:
    r"""Incremental parser of FT 300 stream bytes: feed any chunks, get the valid frames back.

    Pure (no I/O, no clock): the caller timestamps frames. Bytes that do not belong to a valid
    frame are discarded and counted; a frame is emitted only if its CRC matches, so corrupted or
    misaligned data never comes out.

    Example:
        >>> p = StreamParser()
        >>> f = encode_stream_frame([20000, -1, 2, 3, 4, 5])
        >>> p.feed(b"\xff\x20" + f[:7])
        []
        >>> p.feed(f[7:] + f)
        [(20000, -1, 2, 3, 4, 5), (20000, -1, 2, 3, 4, 5)]
        >>> p.stats.frames, p.stats.bytes_discarded, p.stats.resyncs
        (2, 2, 1)
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats = StreamParserStats()
        self._pending_discard = 0

    def reset(self) -> None:
        """Drop buffered bytes (e.g. after a reconnect); counters are kept."""
        self._buf.clear()
        self._pending_discard = 0

    @property
    def buffered(self) -> int:
        """Number of bytes waiting for more input."""
        return len(self._buf)

    def _discard(self, n: int) -> None:
        del self._buf[:n]
        self.stats.bytes_discarded += n
        self._pending_discard += n

    def feed(self, data: bytes | bytearray | memoryview) -> list[tuple[int, ...]]:
        """Append received bytes and return the frames completed by them.

        Args:
            data: Bytes as read from the port, of any length.

        Returns:
            Raw int16 counts ``(Fx, Fy, Fz, Mx, My, Mz)`` of each valid frame, in arrival order.
        """
        self._buf += data
        out: list[tuple[int, ...]] = []
        buf = self._buf
        while True:
            i = buf.find(HEADER)
            if i < 0:
                # keep a trailing 0x20: it may be the first half of a header
                keep = 1 if buf and buf[-1] == HEADER[0] else 0
                self._discard(len(buf) - keep)
                return out
            if i > 0:
                self._discard(i)
            if len(buf) < FRAME_LEN:
                return out
            if crc16_modbus(buf[:14]) == buf[14] | (buf[15] << 8):
                out.append(tuple(np.frombuffer(bytes(buf[2:14]), dtype="<i2").tolist()))
                del buf[:FRAME_LEN]
                self.stats.frames += 1
                if self._pending_discard:
                    self.stats.resyncs += 1
                    self._pending_discard = 0
            else:
                # an aliased or corrupted header: slide one byte, never cut at it
                self.stats.crc_errors += 1
                self._discard(1)

    def take_discarded(self) -> int:
        """Return the bytes discarded since the last valid frame and forget them.

        Used by drivers to estimate how many frames a corruption cost.
        """
        n, self._pending_discard = self._pending_discard, 0
        return n


class GapEstimator:
    """Estimate frames lost in a fixed-rate stream from host arrival times.

    Frames carry no counter, so loss is inferred from time: each frame gets the index
    ``k = max(k_prev + 1, round((t - t0) / period - slack))`` where ``t0`` tracks the earliest
    (least delayed) arrival, so that late arrivals (positive jitter, batching by the OS) never
    look like losses; a small leak lets ``t0`` follow a sensor clock slower than nominal.

    Args:
        period_ns: Nominal frame period in ns (10_000_000 for 100 Hz).
        slack: Extra lateness tolerated, in periods: a frame may arrive up to ``0.5 + slack``
            periods late before a loss is counted.

    Example:
        >>> g = GapEstimator(10_000_000)
        >>> [g.update(t) for t in (0, 10_000_000, 20_500_000, 50_000_000)]
        [0, 0, 0, 2]
    """

    def __init__(self, period_ns: int, slack: float = 0.4) -> None:
        self.period_ns = int(period_ns)
        self.slack = float(slack)
        self.reset()

    def reset(self) -> None:
        """Forget the anchor (after a reconnect or a resync of unknown length)."""
        self._t0: float | None = None
        self._k = 0

    def update(self, t_ns: int) -> int:
        """Register a frame arriving at ``t_ns``; return the number of frames missed before it."""
        if self._t0 is None:
            self._t0, self._k = float(t_ns), 0
            return 0
        est = (t_ns - self._t0) / self.period_ns
        k = max(self._k + 1, int(np.floor(est - self.slack + 0.5)))
        missed = k - self._k - 1
        self._k = k
        # anchor on the least delayed arrival; leak slowly towards later ones (clock drift)
        offset = t_ns - k * self.period_ns
        self._t0 = offset if offset < self._t0 else self._t0 + 1e-3 * (offset - self._t0)
        return missed
