"""Causal joint velocities and accelerations for live use: a one-sided Savitzky-Golay filter.

The log pipeline derives ``qd``, ``qdd`` with a *centred* window
(:func:`torchcontact.logs.derive.savgol_derivatives`: frames on both sides), which needs the
future and cannot run live. Here, for every frame ``i`` a polynomial of degree ``order`` is
fitted by least squares to the last ``window`` frames ``i - window + 1 .. i`` on their real time
stamps (uneven sampling is fine) and evaluated at the newest frame::

    q(t) ~ c0 + c1 (t - t_i) + ... + c_p (t - t_i)^p,   q_i ~ c0,  qd_i = c1,  qdd_i = 2 c2

Only past frames enter, so the same numbers come out live (:class:`CausalDerivatives`, one frame
at a time) and over a log (:func:`causal_derivatives`, batched; needs ``window - 1`` frames of
context before a chunk, none after).

**Delay.** The fit is exact for polynomials of degree ``<= order``, so for slow signals the
delay of ``qd`` is zero (with ``order >= 2``) and so is that of ``qdd`` with ``order >= 3``; with
``order = 2`` the fitted curvature is the average over the window, ``qdd`` then lags by half the
window, ``(window - 1) / 2`` frames. :meth:`CausalDerivatives.delay` gives each output's delay
at any frequency (from the filter's frequency response on a uniform grid), and
:meth:`CausalDerivatives.noise_gain` how white position noise is amplified. The price of no
delay is noise: a one-sided fit amplifies noise more than a centred one of the same window.

The first ``order`` frames of a stream (fewer frames than coefficients) have no estimate: NaN.

Example:
    >>> t = np.arange(30) * 10_000_000  # 100 Hz, ns
    >>> s = t * 1e-9
    >>> q = np.stack([s**3, np.sin(s)], -1)
    >>> qh, qd, qdd = causal_derivatives(t, q, window=9, order=3)
    >>> bool(np.allclose(qd[3:, 0], 3 * s[3:] ** 2) and np.allclose(qdd[3:, 0], 6 * s[3:]))
    True
    >>> f = CausalDerivatives(2, window=9, order=3)
    >>> out = [f.update(ti, qi) for ti, qi in zip(t, q)]
    >>> bool(np.allclose(np.array([o[1] for o in out])[3:], qd[3:]))
    True
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from torchcontact.errors import InputError

__all__ = [
    "DEFAULT_ORDER",
    "DEFAULT_WINDOW",
    "CausalDerivatives",
    "causal_derivatives",
    "savgol_weights",
]

#: Default window, frames (at 100 Hz 0.15 s; at 1 kHz 15 ms).
DEFAULT_WINDOW = 15
#: Default polynomial degree: 3, so that neither ``qd`` nor ``qdd`` lags at low frequency.
DEFAULT_ORDER = 3


def _check(window: int, order: int) -> None:
    if not (isinstance(order, int) and order >= 2):
        raise InputError(f"order must be an integer >= 2 (qdd needs a curvature), got {order!r}")
    if not (isinstance(window, int) and window > order):
        raise InputError(f"window must be an integer > order ({order}), got {window!r}")


def _fit(dt: np.ndarray, q: np.ndarray, order: int) -> tuple[np.ndarray, ...]:
    """Least-squares polynomial on ``dt`` (s, ``(n, W)``, 0 at the newest) of ``q (n, W, nv)``."""
    scale = np.maximum(np.abs(dt).max(-1, keepdims=True), 1e-12)  # conditioning
    s = dt / scale
    V = s[..., None] ** np.arange(order + 1)  # (n, W, p + 1)
    VtV = V.transpose(0, 2, 1) @ V
    Vtq = V.transpose(0, 2, 1) @ q
    c = np.linalg.solve(VtV, Vtq)  # (n, p + 1, nv)
    return c[:, 0], c[:, 1] / scale, 2.0 * c[:, 2] / scale**2


def causal_derivatives(
    t_ns: Any,
    q: Any,
    window: int = DEFAULT_WINDOW,
    order: int = DEFAULT_ORDER,
    lo: int = 0,
    hi: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Causal smoothed positions, velocities and accelerations of a whole log (batched).

    Args:
        t_ns: ``(L,)`` int64 time stamps, ns, increasing.
        q: ``(L, nv)`` positions, rad or m.
        window: frames per fit (the newest and ``window - 1`` before it; fewer at the start).
        order: polynomial degree (>= 2).
        lo: first frame to return.
        hi: one past the last frame to return (default ``L``); pass ``window - 1`` frames of
            context before ``lo`` unless the log starts there (none is needed after ``hi``).

    Returns:
        ``q_hat, qd, qdd``, each ``(hi - lo, nv)``: rad (m), per s, per s^2; NaN for the first
        ``order`` frames of the log (too few frames for the fit).

    Raises:
        InputError: bad window/order, mismatched shapes, time stamps not increasing.
    """
    _check(window, order)
    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    x = np.asarray(q, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] != t.shape[0]:
        raise InputError(f"q must be (L, nv) with L = {t.shape[0]}, got {x.shape}")
    if t.size > 1 and (np.diff(t) <= 0).any():
        raise InputError("time stamps must increase")
    L, nv = x.shape
    hi = L if hi is None else hi
    rows = np.arange(lo, hi)
    out = [np.full((len(rows), nv), np.nan) for _ in range(3)]
    # frames with a full window, then the first ones (shorter windows), each group batched
    for w in sorted({min(window, i + 1) for i in rows}):
        sel = rows[np.minimum(window, rows + 1) == w] if w < window else rows[rows + 1 >= window]
        if w <= order or len(sel) == 0:
            continue
        for s in range(0, len(sel), 16384):  # bounded memory: (n, w, nv) per block
            part = sel[s : s + 16384]
            idx = part[:, None] - np.arange(w - 1, -1, -1)  # (n, w), oldest first
            dt = (t[idx] - t[part][:, None]).astype(np.float64) * 1e-9
            fit = _fit(dt, x[idx], order)
            for o, v in zip(out, fit, strict=True):
                o[part - lo] = v
    return out[0], out[1], out[2]


def savgol_weights(window: int, order: int, period: float) -> np.ndarray:
    """``(3, window)`` weights of the newest-first samples for ``q_hat, qd, qdd`` (uniform grid).

    ``qd_i = sum_k w[1, k] q_{i - k}``: the filter as an FIR on a uniform sample ``period`` (s).
    """
    _check(window, order)
    dt = -np.arange(window, dtype=np.float64) * period
    eye = np.eye(window)[None].transpose(2, 1, 0)  # each sample's unit response, (W, W, 1)
    fits = _fit(np.broadcast_to(dt, (window, window)), eye, order)  # (W, 1) each
    return np.stack([f[:, 0] for f in fits])


class CausalDerivatives:
    """The causal filter one frame at a time (the live loop), equal to :func:`causal_derivatives`.

    Args:
        nv: number of joints.
        window: frames per fit.
        order: polynomial degree (>= 2).

    Example:
        >>> f = CausalDerivatives(1, window=5, order=2)
        >>> qdd = [f.update(k * 1_000_000, [0.5 * (k * 1e-3) ** 2])[2][0] for k in range(4)]
        >>> [round(float(x), 9) for x in qdd]
        [nan, nan, 1.0, 1.0]
    """

    def __init__(self, nv: int, window: int = DEFAULT_WINDOW, order: int = DEFAULT_ORDER) -> None:
        _check(window, order)
        self.nv, self.window, self.order = int(nv), window, order
        self.reset()

    def reset(self) -> None:
        """Forget the history (a gap in the stream)."""
        self._t: deque[int] = deque(maxlen=self.window)
        self._q: deque[np.ndarray] = deque(maxlen=self.window)

    def update(self, t_ns: int, q: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Add a frame and return its ``q_hat, qd, qdd`` ``(nv,)`` (NaN until ``order + 1`` frames).

        Args:
            t_ns: the frame's time stamp, ns (increasing).
            q: ``(nv,)`` positions.

        Raises:
            InputError: a wrong size, a time stamp not after the previous one.
        """
        x = np.asarray(q, dtype=np.float64).reshape(-1)
        if x.shape != (self.nv,):
            raise InputError(f"q must have {self.nv} values, got {x.shape}")
        t = int(t_ns)
        if self._t and t <= self._t[-1]:
            raise InputError(f"time stamp {t} ns is not after the previous one ({self._t[-1]} ns)")
        self._t.append(t)
        self._q.append(x)
        n = len(self._t)
        if n <= self.order:
            nan = np.full(self.nv, np.nan)
            return nan, nan.copy(), nan.copy()
        ts = np.fromiter(self._t, dtype=np.int64, count=n)
        dt = ((ts - t).astype(np.float64) * 1e-9)[None]
        qh, qd, qdd = _fit(dt, np.stack(self._q)[None], self.order)
        return qh[0], qd[0], qdd[0]

    def response(self, freq_hz: Any, period: float) -> np.ndarray:
        """``(3, F)`` complex gains of ``q_hat, qd, qdd`` relative to the ideal ``1, jw, -w^2``.

        Args:
            freq_hz: ``(F,)`` frequencies, Hz (below Nyquist).
            period: uniform sample period, s.
        """
        f = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
        w = 2 * np.pi * f
        k = np.arange(self.window)
        H = savgol_weights(self.window, self.order, period) @ np.exp(-1j * np.outer(k, w) * period)
        ideal = np.stack([np.ones_like(w), 1j * w, -(w**2)]).astype(complex)
        return H / np.where(ideal == 0, 1, ideal)

    def delay(self, period: float, freq_hz: float = 0.0) -> tuple[float, float, float]:
        """Delay (s) of ``q_hat``, ``qd``, ``qdd`` at ``freq_hz`` (0: the low-frequency limit).

        The phase lag of each output against the exact value, divided by the angular
        frequency; 0 means no delay.

        Example:
            >>> [round(d / 0.01, 3) for d in CausalDerivatives(1, 11, 2).delay(0.01)]
            [0.0, 0.0, 5.0]
        """
        f = max(float(freq_hz), 1e-4 / (self.window * period))
        r = self.response([f], period)[:, 0]
        return tuple(float(-np.angle(x) / (2 * np.pi * f)) for x in r)  # type: ignore[return-value]

    def noise_gain(self, period: float) -> tuple[float, float, float]:
        """Standard deviation of ``q_hat, qd, qdd`` per unit of white position noise (uniform)."""
        w = savgol_weights(self.window, self.order, period)
        return tuple(float(math.sqrt((r * r).sum())) for r in w)  # type: ignore[return-value]
