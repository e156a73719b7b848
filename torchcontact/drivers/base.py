"""The common interface of F/T sources: samples, statistics, tare, reconnection with backoff.

A driver implements three hooks (``_connect``, ``_disconnect``, ``_receive``); this base class
turns them into a loop-friendly :meth:`FTSource.read` that never raises on a lost connection:
it returns ``None``, closes the link and re-opens it later with exponential backoff, so the
caller's control loop keeps its rate. Sequence numbers advance by the number of frames the
driver knows were lost, so a gap is visible and a sample is never repeated or invented.
"""

from __future__ import annotations

import abc
import enum
import time
from dataclasses import asdict, dataclass

import numpy as np

from torchcontact.errors import FTConnectionError, FTError  # noqa: F401  (re-exported)


class ConnectionLost(FTError):
    """Raised by a driver's ``_receive`` when the link broke; the base class reconnects."""


class SampleFlags(enum.IntFlag):
    """Flags carried by each :class:`FTSample`."""

    NONE = 0
    #: The software bias from :meth:`FTSource.tare` was subtracted.
    TARED = 1
    #: Frames were lost just before this one (``seq`` jumped by more than one).
    AFTER_GAP = 2
    #: First sample after the connection was re-opened.
    RECONNECTED = 4
    #: Sample came from stream mode (host arrival time), not a polled read.
    STREAM = 8


@dataclass(frozen=True)
class FTSample:
    """One F/T reading.

    Attributes:
        t_ns: Host monotonic time (``time.monotonic_ns``) at which the frame was received, ns.
        seq: Sequence number; increases by 1 per frame, by more when frames were lost.
        wrench: (6,) float64 [force; moment] in N and N m, sensor frame, bias subtracted when
            ``flags & TARED``.
        flags: :class:`SampleFlags`.
    """

    t_ns: int
    seq: int
    wrench: np.ndarray
    flags: SampleFlags = SampleFlags.NONE


@dataclass
class FTStats:
    """Counters of an :class:`FTSource`.

    Attributes:
        frames: Samples returned.
        dropped: Frames known or estimated lost (gaps in a stream, corrupted frames).
        crc_errors: Frames or responses rejected for a bad CRC.
        timeouts: Reads that returned nothing within their timeout.
        reconnects: Successful re-opens after a lost connection.
        connect_failures: Failed open attempts.
        bytes_discarded: Stream bytes discarded while resynchronising.
    """

    frames: int = 0
    dropped: int = 0
    crc_errors: int = 0
    timeouts: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    bytes_discarded: int = 0

    def as_dict(self) -> dict[str, int]:
        """Return the counters as a plain dict."""
        return asdict(self)


class FTSource(abc.ABC):
    """Base class of F/T sources.

    Args:
        name: Sensor name, used as the log column ``ft.<name>``.
        backoff_initial: First reconnect delay after a lost connection, s.
        backoff_max: Cap of the exponential backoff, s.
        max_consecutive_timeouts: After this many timeouts in a row the link is considered lost
            and re-opened (a sensor that was power-cycled stops streaming).
    """

    def __init__(
        self,
        name: str,
        *,
        backoff_initial: float = 0.05,
        backoff_max: float = 2.0,
        max_consecutive_timeouts: int = 5,
    ) -> None:
        self.name = name
        self.stats = FTStats()
        self.bias = np.zeros(6, dtype=np.float64)
        self._tared = False
        self._backoff_initial = backoff_initial
        self._backoff_max = backoff_max
        self._backoff = backoff_initial
        self._max_timeouts = max_consecutive_timeouts
        self._consecutive_timeouts = 0
        self._connected = False
        self._ever_connected = False
        self._next_attempt = 0.0
        self._recovered = False
        self._seq = -1

    # -- hooks -----------------------------------------------------------------------------

    @abc.abstractmethod
    def _connect(self) -> None:
        """Open the link; raise ``OSError`` or :class:`FTError` on failure."""

    @abc.abstractmethod
    def _disconnect(self) -> None:
        """Close the link; must not raise."""

    @abc.abstractmethod
    def _receive(self, timeout: float) -> tuple[int, np.ndarray, int, SampleFlags] | None:
        """Return the next new frame or ``None`` on timeout.

        Returns:
            ``(t_ns, wrench (6,) N and N m, frames missed before it, flags)``.

        Raises:
            ConnectionLost: If the link broke.
        """

    # -- public API ------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the link is currently open."""
        return self._connected

    def open(self) -> None:
        """Open the link now.

        Raises:
            FTConnectionError: Naming the port or host when it cannot be opened.
        """
        try:
            self._connect()
        except (OSError, FTError) as exc:
            self._disconnect()
            raise FTConnectionError(f"{self.describe()}: cannot open: {exc}") from exc
        self._connected = self._ever_connected = True
        self._backoff = self._backoff_initial

    def close(self) -> None:
        """Close the link (idempotent)."""
        if self._connected:
            self._disconnect()
        self._connected = False

    def describe(self) -> str:
        """Human-readable identification of the source (port or host)."""
        return self.name

    def __enter__(self) -> FTSource:
        if not self._connected:
            self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _lose(self) -> None:
        self._disconnect()
        self._connected = False
        self._next_attempt = time.monotonic() + self._backoff
        self._backoff = min(self._backoff * 2.0, self._backoff_max)

    def _try_reconnect(self, timeout: float) -> bool:
        wait = self._next_attempt - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, timeout))
            if wait > timeout:
                return False
        try:
            self._connect()
        except (OSError, FTError):
            self.stats.connect_failures += 1
            self._lose()
            return False
        self._connected = True
        if self._ever_connected:
            self.stats.reconnects += 1
            self._recovered = True
        self._ever_connected = True
        self._backoff = self._backoff_initial
        self._consecutive_timeouts = 0
        return True

    def read(self, timeout: float = 0.1) -> FTSample | None:
        """Return the next new sample, or ``None`` if none arrived within ``timeout``.

        Never raises for a lost link: the link is closed, re-opened with backoff on later
        calls, and the loss is counted in :attr:`stats`. A sample is returned at most once.

        Args:
            timeout: Maximum time to wait, s (a reconnect attempt may add its own open time).

        Returns:
            The sample, or ``None``.
        """
        if not self._connected and not self._try_reconnect(timeout):
            return None
        try:
            got = self._receive(timeout)
        except (ConnectionLost, OSError):
            self._lose()
            return None
        if got is None:
            self.stats.timeouts += 1
            self._consecutive_timeouts += 1
            if self._consecutive_timeouts >= self._max_timeouts:
                self._lose()
            return None
        self._consecutive_timeouts = 0
        t_ns, wrench, missed, flags = got
        if missed > 0:
            flags |= SampleFlags.AFTER_GAP
            self.stats.dropped += missed
        if self._recovered:
            flags |= SampleFlags.RECONNECTED
            self._recovered = False
        self._seq += 1 + max(missed, 0)
        self.stats.frames += 1
        wrench = np.asarray(wrench, dtype=np.float64)
        if self._tared:
            wrench = wrench - self.bias
            flags |= SampleFlags.TARED
        return FTSample(t_ns=t_ns, seq=self._seq, wrench=wrench, flags=flags)

    def tare(self, n: int = 100, timeout: float = 5.0) -> np.ndarray:
        """Zero the sensor in software: average ``n`` new samples and subtract them from now on.

        Args:
            n: Number of samples to average.
            timeout: Total time allowed, s.

        Returns:
            (6,) float64 bias [force; moment] in N and N m, sensor frame.

        Raises:
            FTError: If fewer than ``n`` samples arrived within ``timeout``.
        """
        if n < 1:
            raise ValueError(f"tare needs n >= 1 samples, got {n}")
        deadline = time.monotonic() + timeout
        total = np.zeros(6, dtype=np.float64)
        got = 0
        while got < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise FTError(f"{self.describe()}: tare got {got} of {n} samples in {timeout} s")
            s = self.read(min(left, 0.2))
            if s is not None:
                total += s.wrench + (self.bias if s.flags & SampleFlags.TARED else 0.0)
                got += 1
        self.bias = total / n
        self._tared = True
        return self.bias.copy()

    def untare(self) -> None:
        """Forget the software bias."""
        self.bias = np.zeros(6, dtype=np.float64)
        self._tared = False
