"""Joint velocities and accelerations from logged positions: a Savitzky-Golay differentiator.

For every frame ``i`` a quadratic ``q(t) ~ c0 + c1 (t - t_i) + c2 (t - t_i)^2`` is fitted by least
squares to the ``2 h + 1`` frames ``i - h .. i + h`` (their real time stamps ``t_ns``, so uneven
sampling is fine), and ``qd_i = c1``, ``qdd_i = 2 c2``. At the ends of a log the window is shifted
inwards so it keeps ``2 h + 1`` frames. This is Savitzky-Golay (Savitzky and Golay 1964) with
polynomial order 2 evaluated on the actual time stamps.

Time segments: a fit needs strictly increasing stamps. :func:`time_segments` cuts a log at every
repeated or backward ``t_ns`` and at every gap longer than :data:`GAP_FACTOR` times the log's
median step (:func:`median_step`); windows never cross a segment boundary (they are shifted inwards
at segment ends as at the log's ends), and a segment of fewer than :data:`MIN_SEGMENT_FRAMES`
frames cannot be differentiated (NaN).

Causal (``estimate --derivatives causal``): :class:`DerivativeStream` with ``causal=(window,
order)`` runs the live loop's one-sided differentiator
(:func:`torchcontact.online.derivatives.causal_derivatives`) within each time segment instead, so
an offline estimate sees the derivatives the robot computes online (with their delay).

Streaming (:class:`DerivativeStream`): a frame's window lies within ``2 h`` frames of it (``h``
each side, shifted by up to ``h`` at a segment end), so the pipeline carries ``2 h`` frames of
context before and after each chunk; results do not depend on the chunking.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "DEFAULT_HALF_WINDOW",
    "GAP_FACTOR",
    "MIN_SEGMENT_FRAMES",
    "DerivativeStream",
    "median_step",
    "savgol_derivatives",
    "step_histogram",
    "time_segments",
]

#: Default half window ``h`` (frames); 11 frames = 0.11 s at 100 Hz.
DEFAULT_HALF_WINDOW = 5

#: A step of ``t_ns`` longer than this many median steps starts a new segment.
GAP_FACTOR = 5.0

#: Fewest frames of a segment that a quadratic can be fitted to (its three coefficients).
MIN_SEGMENT_FRAMES = 3


def time_segments(t_ns: np.ndarray, step_ns: float) -> np.ndarray:
    """Where new time segments start: at untrusted stamps and at gaps.

    A frame whose stamp does not increase over its predecessor's (repeated or backward
    ``t_ns``) cannot be placed in time: it becomes a segment of its own (a segment starts at it
    and at the frame after it). A step longer than :data:`GAP_FACTOR` median steps starts a
    segment too.

    Args:
        t_ns: ``(L,)`` int64 time stamps, ns. To continue an earlier array, prepend its last two
            stamps and drop the first two results.
        step_ns: the log's median step, ns (:func:`median_step`; 0: no gap rule).

    Returns:
        ``(L,)`` bool, True where a frame starts a segment (frame 0 does).

    Example:
        >>> time_segments(np.array([0, 10, 20, 20, 30, 40, 100, 110]), 10.0).tolist()
        [True, False, False, True, True, False, True, False]
    """
    t = np.asarray(t_ns, np.int64)
    out = np.zeros(len(t), bool)
    if len(t):
        out[0] = True
        step = np.diff(t)
        back = step <= 0  # frame i + 1 does not advance over frame i
        out[1:] = back
        if step_ns > 0:
            out[1:] |= step > GAP_FACTOR * step_ns
        out[2:] |= back[:-1]  # the frame after an untrusted one starts afresh
    return out


def median_step(steps: dict[int, int]) -> float:
    """The median of positive time steps from a histogram ``{step in us: count}``, in ns.

    Args:
        steps: counts of the positive steps of a log, rounded to microseconds (see
            :func:`step_histogram`); a log is scanned in blocks and their histograms added.

    Returns:
        The median step, ns (0 when the log has no positive step).

    Example:
        >>> median_step({10_000: 5, 20_000: 1})
        10000000.0
    """
    if not steps:
        return 0.0
    keys = np.array(sorted(steps), np.int64)
    counts = np.array([steps[k] for k in keys], np.int64)
    cum = np.cumsum(counts)
    return float(keys[int(np.searchsorted(cum, (cum[-1] + 1) // 2))]) * 1e3


def step_histogram(t_ns: np.ndarray, into: dict[int, int]) -> None:
    """Add the positive steps of ``t_ns`` (rounded to microseconds) to a histogram."""
    step = np.diff(np.asarray(t_ns, np.int64))
    step = step[step > 0]
    if len(step):
        us, n = np.unique(np.maximum((step + 500) // 1000, 1), return_counts=True)
        for k, c in zip(us.tolist(), n.tolist(), strict=True):
            into[k] = into.get(k, 0) + c


def savgol_derivatives(
    t_ns: np.ndarray,
    q: np.ndarray,
    half_window: int = DEFAULT_HALF_WINDOW,
    lo: int = 0,
    hi: int | None = None,
    starts: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """First and second time derivatives of ``q`` by local quadratic least squares.

    Args:
        t_ns: ``(L,)`` int64 time stamps, ns, increasing within each segment.
        q: ``(L, nv)`` positions (rad or m).
        half_window: ``h``; the window holds ``2 h + 1`` frames (fewer when a segment is
            shorter).
        lo: first frame to return.
        hi: one past the last frame to return (default ``L``). Windows are clamped to ``[0, L)``:
            pass ``2 h`` frames of context on each side of ``[lo, hi)`` unless the log ends there.
        starts: ``(L,)`` bool, True where a time segment starts (:func:`time_segments`); None:
            one segment. A window stays inside its frame's segment.

    Returns:
        ``qd`` ``(hi - lo, nv)`` per second and ``qdd`` ``(hi - lo, nv)`` per second squared; NaN
        for frames whose segment has fewer than :data:`MIN_SEGMENT_FRAMES` frames.

    Example:
        >>> t = np.arange(20) * 10_000_000  # 100 Hz
        >>> s = t * 1e-9
        >>> qd, qdd = savgol_derivatives(t, np.stack([s**2, 3 * s], -1))
        >>> np.allclose(qd[:, 0], 2 * s) and np.allclose(qdd, [2.0, 0.0])
        True
    """
    L = len(t_ns)
    hi = L if hi is None else hi
    n = hi - lo
    nv = q.shape[-1]
    if n <= 0:
        return np.zeros((0, nv)), np.zeros((0, nv))
    rows = np.arange(lo, hi)
    if starts is None:
        seg_lo, seg_hi = np.zeros(n, np.int64), np.full(n, L, np.int64)
    else:
        # each frame's segment [seg_lo, seg_hi) from the segment starts (vectorised)
        start_idx = np.flatnonzero(starts)
        if not len(start_idx) or start_idx[0] != 0:
            start_idx = np.r_[0, start_idx]
        sid = np.searchsorted(start_idx, rows, side="right") - 1
        ends = np.r_[start_idx[1:], L]
        seg_lo, seg_hi = start_idx[sid], ends[sid]
    Wmax = 2 * half_window + 1
    W = np.minimum(Wmax, seg_hi - seg_lo)  # frames of each row's window
    qd, qdd = np.full((n, nv), np.nan), np.full((n, nv), np.nan)
    fit = W >= MIN_SEGMENT_FRAMES
    if not fit.any():
        return qd, qdd
    rows, seg_lo, seg_hi, W = rows[fit], seg_lo[fit], seg_hi[fit], W[fit]
    Wc = int(W.max())
    start = np.clip(rows - half_window, seg_lo, seg_hi - W)
    idx = start[:, None] + np.arange(Wc)  # (m, Wc); columns >= W are masked out
    inside = np.arange(Wc)[None, :] < W[:, None]
    idx = np.where(inside, idx, rows[:, None])
    t0 = t_ns[rows]
    dt = (t_ns[idx] - t0[:, None]).astype(np.float64) * 1e-9  # s, (m, Wc)
    scale = np.maximum(np.abs(dt).max(-1, keepdims=True), 1e-12)  # conditioning
    s = dt / scale
    V = np.stack([np.ones_like(s), s, s * s], -1) * inside[..., None]  # (m, Wc, 3)
    VtV = V.transpose(0, 2, 1) @ V
    Vtq = V.transpose(0, 2, 1) @ q[idx]  # (m, 3, nv)
    c = np.linalg.solve(VtV, Vtq)
    qd[fit], qdd[fit] = c[:, 1] / scale, 2.0 * c[:, 2] / scale**2
    return qd, qdd


class DerivativeStream:
    """Derivatives of consecutive chunks of one log, with ``2 h`` frames of context each side.

    Args:
        half_window: ``h`` of :func:`savgol_derivatives`.
        step_ns: the log's median step (:func:`median_step`) for the gap rule.
        before: ``(t_ns, q)`` of the up to ``2 h`` frames preceding the first chunk (model order),
            or None at the log's start.

    Example:
        >>> t = np.arange(30) * 10_000_000
        >>> q = (t * 1e-9)[:, None] ** 2
        >>> ds = DerivativeStream(2, 1e7)
        >>> parts = [ds.derive(t[a:b], q[a:b], t[b:b + 4], q[b:b + 4]) for a, b in
        ...          ((0, 7), (7, 20), (20, 30))]
        >>> np.allclose(np.concatenate([p[0] for p in parts])[:, 0], 2 * t * 1e-9)
        True
    """

    def __init__(
        self,
        half_window: int,
        step_ns: float,
        before: tuple[np.ndarray, np.ndarray] | None = None,
        causal: tuple[int, int] | None = None,
    ) -> None:
        self.h = half_window
        self.step_ns = step_ns
        self.causal = causal
        self._t, self._q = before if before is not None else (np.zeros(0, np.int64), None)

    @property
    def context(self) -> tuple[int, int]:
        """Context frames ``(before, after)``: ``(2 h, 2 h)``; causal ``(window - 1, 0)``."""
        if self.causal is not None:
            return self.causal[0] - 1, 0
        return 2 * self.h, 2 * self.h

    def derive(
        self, t_ns: np.ndarray, q: np.ndarray, t_next: np.ndarray, q_next: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Derivatives of one chunk; ``t_next``/``q_next``: the frames after it.

        Args:
            t_ns: ``(N,)`` stamps of the chunk.
            q: ``(N, nv)`` positions, model order.
            t_next: stamps of the up to ``2 h`` frames that follow the chunk (empty at the end).
            q_next: their positions.

        Returns:
            ``qd``, ``qdd`` ``(N, nv)``, ``starts`` ``(N,)`` bool (a frame starts a time
            segment; the log's first frame does) and ``length`` ``(N,)`` int64, the frames of
            each frame's segment as far as the context shows (exact below ``2 h + 1``).
        """
        c, c_after = self.context
        prev_t = self._t
        prev_q = self._q if self._q is not None else np.zeros((0, q.shape[1]))
        t_all = np.concatenate([prev_t, t_ns, t_next[:c_after]])
        q_all = np.concatenate([prev_q, q, q_next[:c_after]])
        starts = time_segments(t_all, self.step_ns)
        lo, hi = len(prev_t), len(prev_t) + len(t_ns)
        seg = np.cumsum(starts) - 1
        if self.causal is None:
            qd, qdd = savgol_derivatives(t_all, q_all, self.h, lo, hi, starts)
            length = np.bincount(seg)[seg]
        else:
            qd, qdd, length = _causal(t_all, q_all, starts, seg, lo, hi, *self.causal)
        self._t = np.concatenate([prev_t, t_ns])[-c:] if c else prev_t[:0]
        self._q = np.concatenate([prev_q, q])[-c:] if c else prev_q[:0]
        return qd, qdd, starts[lo:hi], length[lo:hi]


def _causal(
    t: np.ndarray,
    q: np.ndarray,
    starts: np.ndarray,
    seg: np.ndarray,
    lo: int,
    hi: int,
    window: int,
    order: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The online causal differentiator on frames ``lo .. hi - 1``, restarted at each segment.

    :func:`torchcontact.online.derivatives.causal_derivatives` (the one the live loop runs) on
    each time segment's frames; ``length`` per frame of ``t`` is the frames of its segment up to
    it, 0 where they are too few for the fit (``<= order``: its derivatives are NaN).
    """
    from torchcontact.online.derivatives import causal_derivatives

    nv = q.shape[1]
    qd, qdd = np.full((hi - lo, nv), np.nan), np.full((hi - lo, nv), np.nan)
    first = np.flatnonzero(starts)
    pos = np.arange(len(t)) - first[seg]  # index of each frame in its segment
    length = np.where(pos >= order, pos + 1, 0)
    for a, b in zip(first, [*first[1:], len(t)], strict=True):
        a0, b0 = max(a, lo), min(b, hi)
        if a0 >= b0:
            continue
        _, d1, d2 = causal_derivatives(t[a:b0], q[a:b0], window, order, a0 - a, b0 - a)
        qd[a0 - lo : b0 - lo], qdd[a0 - lo : b0 - lo] = d1, d2
    return qd, qdd, length
