"""Joint velocities and accelerations from logged positions: a Savitzky-Golay differentiator.

For every frame ``i`` a quadratic ``q(t) ~ c0 + c1 (t - t_i) + c2 (t - t_i)^2`` is fitted by least
squares to the ``2 h + 1`` frames ``i - h .. i + h`` (their real time stamps ``t_ns``, so uneven
sampling is fine), and ``qd_i = c1``, ``qdd_i = 2 c2``. At the ends of a log the window is shifted
inwards so it keeps ``2 h + 1`` frames. This is Savitzky-Golay (Savitzky and Golay 1964) with
polynomial order 2 evaluated on the actual time stamps.

Streaming: a frame's derivative depends on ``h`` frames on either side, so the pipeline carries
``h`` frames of context before and after each chunk; results do not depend on the chunking.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DEFAULT_HALF_WINDOW", "savgol_derivatives"]

#: Default half window ``h`` (frames); 11 frames = 0.11 s at 100 Hz.
DEFAULT_HALF_WINDOW = 5


def savgol_derivatives(
    t_ns: np.ndarray,
    q: np.ndarray,
    half_window: int = DEFAULT_HALF_WINDOW,
    lo: int = 0,
    hi: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """First and second time derivatives of ``q`` by local quadratic least squares.

    Args:
        t_ns: ``(L,)`` int64 time stamps, ns, increasing.
        q: ``(L, nv)`` positions (rad or m).
        half_window: ``h``; the window holds ``2 h + 1`` frames (fewer when ``L`` is smaller).
        lo: first frame to return.
        hi: one past the last frame to return (default ``L``). Windows are clamped to ``[0, L)``:
            pass ``h`` frames of context on each side of ``[lo, hi)`` unless the log ends there.

    Returns:
        ``qd`` ``(hi - lo, nv)`` per second and ``qdd`` ``(hi - lo, nv)`` per second squared.

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
    W = min(2 * half_window + 1, L)
    if W < 3:  # one or two frames: no curvature to fit
        return np.full((n, nv), np.nan), np.full((n, nv), np.nan)
    rows = np.arange(lo, hi)
    start = np.clip(rows - half_window, 0, L - W)
    idx = start[:, None] + np.arange(W)  # (n, W)
    t0 = t_ns[rows]
    dt = (t_ns[idx] - t0[:, None]).astype(np.float64) * 1e-9  # s, (n, W)
    scale = np.maximum(np.abs(dt).max(-1, keepdims=True), 1e-12)  # conditioning
    s = dt / scale
    V = np.stack([np.ones_like(s), s, s * s], -1)  # (n, W, 3)
    VtV = V.transpose(0, 2, 1) @ V
    Vtq = V.transpose(0, 2, 1) @ q[idx]  # (n, 3, nv)
    c = np.linalg.solve(VtV, Vtq)
    return c[:, 1] / scale, 2.0 * c[:, 2] / scale**2
