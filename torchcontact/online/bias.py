"""F/T bias tracked from the robot model: a Kalman filter on each sensor's offset (numpy only).

An F/T sensor's offset drifts (temperature, creep, a re-mounted cable). While no contact acts on
a sensor's subtree, its reading should equal what the model predicts
(:meth:`ContactEstimator.predict_ft <torchcontact.ContactEstimator.predict_ft>`, plus the
correction stack's inertial layer and the payload), so the *residual*
``z = ft - ft_model`` measures the offset ``o``. The filter models the offset as a random walk
and the residual as the offset plus the sensor's white noise::

    o_k = o_{k-1} + w_k,   w_k ~ N(0, q dt_k / period * R)
    z_k = o_k + v_k,       v_k ~ N(0, R)          (R: the F/T noise covariance, 6 x 6)

Because the process noise is proportional to ``R``, the covariance stays ``P_k = p_k R`` with a
scalar ``p_k`` per sensor, and the filter is a scalar-gain update ``o += K (z - o)`` with
``K = p^- / (p^- + 1)``: the same gain on every axis, whatever ``R``. ``q`` is chosen so that at
the nominal sample ``period`` the steady-state filter is a first-order low-pass with the stated
**time constant** ``tau`` (an offset step decays as ``exp(-t / tau)`` while contact-free):
``beta = exp(-period / tau)``, ``q = (1 - beta)^2 / beta``. ``R`` only sets the reported
uncertainty and the innovation gate.

**Gating.** The offset is updated only on frames the caller marks contact-free (for a sensor: no
active skin contact in its region, no localized contact, and the user's ``contact_free`` signal,
see :class:`torchcontact.online.state.OnlineState`); frames with a non-finite residual are
skipped. Optionally an innovation gate (``gate``, a chi-square threshold with 6 degrees of
freedom on ``(z - o)^T ((p^- + 1) R)^-1 (z - o)``) also rejects contact-free frames that do not
fit (an unreported contact, a transient); ``gate_frames`` rejected frames in a row are taken as
a real change of the offset, which is then re-acquired (``p`` reset to ``prior_scale``).

Offline, the whole log is known: :func:`smooth_bias` runs the same filter forward and the
Rauch-Tung-Striebel smoother backward (Rauch, Tung and Striebel 1965), so frames inside a
contact get the offset interpolated from the contact-free frames on both sides.

Example:
    >>> import numpy as np
    >>> tr = BiasTracker(["ft"], time_constant=0.1, period=0.01)
    >>> for k in range(100):  # 1 s of contact-free frames reading a 2 N offset on fx
    ...     s = tr.update(np.array([2.0, 0, 0, 0, 0, 0]), contact_free=True)
    >>> round(float(s.offset[0, 0]), 6), bool(s.updated[0]), float(s.since_update[0])
    (2.0, True, 0.0)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from torchcontact.errors import InputError

__all__ = [
    "DEFAULT_FT_STD",
    "BiasSmoother",
    "BiasState",
    "BiasTrack",
    "BiasTracker",
    "process_noise",
    "smooth_bias",
]

#: Default F/T noise standard deviations ``[N; N m]`` (only the reported uncertainty and the
#: innovation gate depend on it, not the filter's gain).
DEFAULT_FT_STD = (0.05, 0.05, 0.05, 0.005, 0.005, 0.005)
#: Default time constant, s.
DEFAULT_TIME_CONSTANT = 0.5
#: Chi-square 99.9 % quantile with 6 degrees of freedom (a gate that rejects 1 frame in 1000).
CHI2_6_999 = 22.4577


def process_noise(time_constant: float, period: float) -> float:
    """Process noise per nominal period (in units of ``R``) giving the stated time constant.

    The steady-state gain of the scalar filter is then ``K = 1 - exp(-period / time_constant)``,
    so an offset step decays as ``exp(-t / time_constant)`` at that sample period.

    Args:
        time_constant: s (> 0).
        period: nominal sample period, s (> 0).

    Returns:
        ``q = (1 - beta)^2 / beta`` with ``beta = exp(-period / time_constant)``.

    Example:
        >>> q = process_noise(0.5, 0.01)
        >>> pm = q / 2 + math.sqrt(q * q / 4 + q)  # steady-state prior variance
        >>> round(pm / (pm + 1), 6) == round(1 - math.exp(-0.01 / 0.5), 6)
        True
    """
    if not (time_constant > 0 and period > 0 and math.isfinite(time_constant / period)):
        raise InputError(
            f"time_constant and period must be positive, got {time_constant!r}, {period!r}"
        )
    beta = math.exp(-period / time_constant)
    return (1.0 - beta) ** 2 / beta


def _noise_cov(S: int, ft_std: Any, ft_cov: Any) -> np.ndarray:
    """``(S, 6, 6)`` F/T noise covariances from standard deviations or covariances."""
    if ft_std is not None and ft_cov is not None:
        raise InputError("give ft_std or ft_cov, not both")
    if ft_cov is not None:
        R = np.asarray(ft_cov, dtype=np.float64)
        if R.shape == (6, 6):
            R = np.broadcast_to(R, (S, 6, 6))
        if R.shape != (S, 6, 6):
            raise InputError(f"ft_cov must be (6, 6) or ({S}, 6, 6), got {R.shape}")
    else:
        std = np.asarray(DEFAULT_FT_STD if ft_std is None else ft_std, dtype=np.float64)
        if std.shape == (6,):
            std = np.broadcast_to(std, (S, 6))
        if std.shape != (S, 6):
            raise InputError(f"ft_std must be (6,) or ({S}, 6), got {std.shape}")
        R = np.zeros((S, 6, 6))
        R[:, range(6), range(6)] = std**2
    R = np.array(R)
    if not np.isfinite(R).all() or not np.allclose(R, R.transpose(0, 2, 1)):
        raise InputError("the F/T noise covariance must be finite and symmetric")
    if (np.linalg.eigvalsh(R) <= 0).any():
        raise InputError("the F/T noise covariance must be positive definite")
    return R


def _per_sensor(x: Any, S: int, name: str, dtype: Any = bool) -> np.ndarray:
    a = np.asarray(x, dtype=dtype)
    if a.ndim == 0:
        return np.full(S, a.item(), dtype=dtype)
    if a.shape != (S,):
        raise InputError(f"{name} must be a scalar or ({S},), got {a.shape}")
    return a


class BiasState(NamedTuple):
    """The tracked offsets after a frame (an output of every step).

    Attributes:
        offset: ``(S, 6)`` offset ``[N; N m]`` per sensor (sensor frame and direction): what is
            subtracted from the reading.
        scale: ``(S,)`` its covariance in units of ``R`` (see :attr:`cov`).
        R: ``(S, 6, 6)`` the F/T noise covariance (shared, not copied).
        since_update: ``(S,)`` seconds since the last update (``inf`` before the first).
        updated: ``(S,)`` True where this frame updated the offset.
    """

    offset: np.ndarray
    scale: np.ndarray
    R: np.ndarray
    since_update: np.ndarray
    updated: np.ndarray

    @property
    def cov(self) -> np.ndarray:
        """``(S, 6, 6)`` the offset's covariance ``scale R``."""
        return self.scale[:, None, None] * self.R

    def as_dict(self, sensors: Sequence[str]) -> dict[str, dict[str, Any]]:
        """JSON-ready per sensor: ``offset`` (6), ``std`` (6), ``since_update``, ``updated``."""
        out = {}
        for i, s in enumerate(sensors):
            since = float(self.since_update[i])
            out[s] = {
                "offset": self.offset[i].tolist(),
                "std": np.sqrt(np.diagonal(self.cov[i])).tolist(),
                "since_update": since if math.isfinite(since) else None,
                "updated": bool(self.updated[i]),
            }
        return out


class BiasTracker:
    """Online Kalman filter on each F/T sensor's offset, updated on contact-free frames.

    Args:
        sensors: sensor names (their order is the ``S`` axis of every array).
        time_constant: s, the filter's time constant at the nominal ``period`` (see the module).
        period: nominal sample period, s (used when a frame gives no time stamp).
        ft_std: ``(6,)`` or ``(S, 6)`` noise standard deviations ``[N; N m]`` (default
            :data:`DEFAULT_FT_STD`), or
        ft_cov: ``(6, 6)`` or ``(S, 6, 6)`` noise covariances.
        offset: ``(S, 6)`` initial offsets (default zeros), e.g. a checkpoint's offset layer.
        prior_scale: initial covariance in units of ``R`` (large: the first contact-free frames
            set the offset).
        gate: innovation gate, a chi-square threshold on 6 degrees of freedom (e.g.
            :data:`CHI2_6_999`), or None (contact gating only).
        gate_frames: rejected contact-free frames in a row after which the offset is re-acquired.

    Raises:
        InputError: bad sizes, a non-positive time constant, period or covariance.
    """

    def __init__(
        self,
        sensors: Sequence[str],
        *,
        time_constant: float = DEFAULT_TIME_CONSTANT,
        period: float = 0.01,
        ft_std: Any = None,
        ft_cov: Any = None,
        offset: Any = None,
        prior_scale: float = 1e4,
        gate: float | None = None,
        gate_frames: int = 10,
    ) -> None:
        self.sensors = tuple(sensors)
        S = len(self.sensors)
        if S == 0:
            raise InputError("BiasTracker needs at least one sensor")
        self.time_constant, self.period = float(time_constant), float(period)
        self.q_rate = process_noise(self.time_constant, self.period) / self.period  # per s
        self.R = _noise_cov(S, ft_std, ft_cov)
        self._R_inv = np.linalg.inv(self.R)
        if not prior_scale > 0:
            raise InputError(f"prior_scale must be > 0, got {prior_scale!r}")
        if gate is not None and not gate > 0:
            raise InputError(f"gate must be a positive chi-square threshold, got {gate!r}")
        if gate_frames < 1:
            raise InputError(f"gate_frames must be >= 1, got {gate_frames!r}")
        self.prior_scale, self.gate, self.gate_frames = float(prior_scale), gate, int(gate_frames)
        self._offset0 = np.zeros((S, 6)) if offset is None else self._residual(offset, "offset")
        self.reset()

    def reset(self, offset: Any = None) -> None:
        """Start afresh from ``offset`` (default: the initial offsets) with the prior covariance."""
        S = len(self.sensors)
        self.offset = self._offset0.copy() if offset is None else self._residual(offset, "offset")
        self.p = np.full(S, self.prior_scale)
        self.since = np.full(S, np.inf)
        self.updated = np.zeros(S, dtype=bool)
        self.t: float | None = None
        self._rejected = np.zeros(S, dtype=np.int64)

    def _residual(self, z: Any, name: str = "residual") -> np.ndarray:
        S = len(self.sensors)
        a = np.asarray(z, dtype=np.float64)
        if a.shape == (6,) and S == 1:
            a = a.reshape(1, 6)
        if a.shape != (S, 6):
            raise InputError(f"{name} must be ({S}, 6) [N; N m] per sensor, got {a.shape}")
        return a.copy()

    @property
    def state(self) -> BiasState:
        """The current :class:`BiasState` (copies)."""
        return BiasState(self.offset.copy(), self.p.copy(), self.R, self.since.copy(),
                         self.updated.copy())  # fmt: skip

    def _advance(self, t: float | None) -> float:
        """Move the clock to ``t`` (s; None: one nominal period); returns the step, s."""
        if t is None:
            dt = self.period if self.t is not None else 0.0
            self.t = (self.t or 0.0) + dt
            return dt
        t = float(t)
        if not math.isfinite(t):
            raise InputError(f"time stamp must be finite, got {t!r}")
        dt = 0.0 if self.t is None else t - self.t
        if dt < 0:
            raise InputError(f"time stamps must not decrease ({t} s after {self.t} s)")
        self.t = t
        return dt

    def update(self, residual: Any, contact_free: Any = True, t: float | None = None) -> BiasState:
        """One frame: predict to ``t``, then update each contact-free sensor with its residual.

        Args:
            residual: ``(S, 6)`` (or ``(6,)`` for one sensor) ``ft - ft_model`` ``[N; N m]``:
                the raw reading less the model's contact-free prediction (with the inertial
                layer and payload), not less the offset.
            contact_free: bool, or ``(S,)`` per sensor: whether the frame may update it.
            t: the frame's time, s (monotonic; None: one nominal period after the last frame).

        Returns:
            The :class:`BiasState` after the frame.

        Raises:
            InputError: a wrong shape, a time stamp going backwards.
        """
        z = residual
        if not (type(z) is np.ndarray and z.shape == self.offset.shape and z.dtype == np.float64):
            z = self._residual(z)
        S = len(self.sensors)
        if contact_free is True or contact_free is False:
            free = [contact_free] * S
        elif type(contact_free) is np.ndarray and contact_free.shape == (S,):
            free = contact_free.tolist()
        else:
            free = _per_sensor(contact_free, S, "contact_free").tolist()
        dt = self._advance(t)
        qdt = self.q_rate * dt
        off, p, since, rej = self.offset, self.p, self.since, self._rejected
        updated = [False] * S
        zs, offs = z.tolist(), off.tolist()  # a few sensors of 6 values: Python floats
        for i in range(S):
            # predict: the random walk spreads the uncertainty
            pi = float(p[i]) + qdt
            since[i] += dt
            if free[i]:
                innov = [a - b for a, b in zip(zs[i], offs[i], strict=True)]
                if not math.isfinite(sum(innov)):  # a NaN reading or model output: skip it
                    p[i] = pi
                    continue
                if self.gate is not None:
                    e = np.array(innov)
                    d2 = float(e @ self._R_inv[i] @ e) / (pi + 1.0)
                    if d2 > self.gate:
                        rej[i] += 1
                        if rej[i] < self.gate_frames:
                            p[i] = pi
                            continue
                        pi, rej[i] = self.prior_scale, 0  # a real change: re-acquire it
                    else:
                        rej[i] = 0
                # update: scalar gain, the same on every axis (P = p R)
                g = pi / (pi + 1.0)
                off[i] = [o + g * d for o, d in zip(offs[i], innov, strict=True)]
                pi *= 1.0 - g
                since[i] = 0.0
                updated[i] = True
            p[i] = pi
        self.updated = upd = np.array(updated)  # a new array each frame: shared, not copied
        return BiasState(off.copy(), p.copy(), self.R, since.copy(), upd)

    def tare(self, residual: Any, contact_free: Any = True, frames: int = 1) -> BiasState:
        """Re-zero now: the offset becomes the residual (at the current pose, from the model).

        Args:
            residual: ``(S, 6)`` ``ft - ft_model`` of the current frame, or ``(n, S, 6)``: the
                mean of the last ``n`` frames.
            contact_free: bool or ``(S,)``, or ``(n,)``/``(n, S)`` for several frames: every
                frame must be contact-free for every sensor.
            frames: how many frames ``residual`` holds (its variance is ``R / frames``).

        Raises:
            InputError: a contact is active (the model cannot predict the reading then), or a
                non-finite residual.
        """
        S = len(self.sensors)
        z = np.asarray(residual, dtype=np.float64).reshape(-1, S, 6)
        free = np.broadcast_to(np.asarray(contact_free, dtype=bool), (z.shape[0], S))
        if not free.all():
            busy = [s for i, s in enumerate(self.sensors) if not free[:, i].all()]
            raise InputError(
                f"tare() refused: a contact is active on sensor(s) {busy}; re-zero while the"
                " robot is free of contacts (the model predicts the reading only then)"
            )
        if not np.isfinite(z).all():
            raise InputError("tare() refused: the current reading or joint state is not finite")
        self.offset = z.mean(0)
        self.p = np.full(S, 1.0 / max(int(frames), z.shape[0]))
        self.since = np.zeros(S)
        self.updated = np.ones(S, dtype=bool)
        self._rejected[:] = 0
        return self.state


class BiasTrack(NamedTuple):
    """Offsets over a whole log (:func:`smooth_bias`).

    Attributes:
        offset: ``(N, S, 6)`` offset per frame ``[N; N m]``.
        scale: ``(N, S)`` its covariance in units of ``R`` (``cov = scale[..., None, None] * R``).
        R: ``(S, 6, 6)`` the F/T noise covariance.
        updated: ``(N, S)`` frames that measured the offset (contact-free, finite).
        since_update: ``(N, S)`` s since the last such frame, causally (``inf`` before).
    """

    offset: np.ndarray
    scale: np.ndarray
    R: np.ndarray
    updated: np.ndarray
    since_update: np.ndarray

    def std(self) -> np.ndarray:
        """``(N, S, 6)`` standard deviation of each component."""
        return np.sqrt(self.scale[..., None] * np.diagonal(self.R, axis1=-2, axis2=-1))


def _affine_scan(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Prefix compositions of the affine maps ``x -> a_k x + b_k`` along the first axis.

    Returns ``(A, B)`` with ``x_k = A_k x_0 + B_k`` for ``x_k = a_k x_{k-1} + b_k`` (Hillis and
    Steele's scan: ``log2 n`` passes over the arrays instead of ``n`` steps in Python).

    Args:
        a: ``(n, ...)`` factors (broadcasting against ``b``).
        b: ``(n, ...)`` terms.
    """
    A, B = np.array(a, np.float64), np.array(b, np.float64)
    s = 1
    while s < len(A):
        B[s:] = A[s:] * B[:-s] + B[s:]
        A[s:] = A[s:] * A[:-s]
        s *= 2
    return A, B


class BiasSmoother:
    """The forward filter and the RTS smoother over a log fed chunk by chunk (bounded memory).

    :func:`smooth_bias` for logs too long to hold: :meth:`forward` takes consecutive chunks of
    residuals and appends each frame's filter state (``S * 6`` offsets and ``2 S`` variances,
    float64: ``64 S`` bytes a frame) to ``store``, a file (None: memory); :meth:`smooth` runs
    the backward pass over it in blocks read and written back in place; :meth:`offsets` reads
    any rows back. The process holds a block of frames at a time whatever the log's length (no
    memory map: plain reads and writes); the file holds ``64 S`` bytes per frame (1M frames, one
    sensor: 64 MB) and is the caller's to delete.

    The gains depend only on which frames are contact-free and on the time steps, as in
    :func:`smooth_bias`, which is this class run on one chunk in memory.

    Args:
        sensors: ``S``, the number of sensors.
        time_constant: s, as :class:`BiasTracker`.
        period: nominal period, s (the log's median step).
        ft_std: as :class:`BiasTracker`.
        ft_cov: as :class:`BiasTracker`.
        offset: ``(S, 6)`` prior offset before the first frame (default zeros).
        prior_scale: its covariance in units of ``R``.
        store: file for the per-frame states (created, truncated), or None (memory).

    Raises:
        InputError: a non-positive time constant or period, a bad covariance or offset.

    Example:
        >>> import numpy as np
        >>> z = np.zeros((300, 1, 6)); z[:, 0, 0] = np.linspace(0.0, 3.0, 300)
        >>> free = np.ones((300, 1), bool); free[100:200] = False
        >>> sm = BiasSmoother(1, time_constant=0.2, period=0.01)
        >>> for a in range(0, 300, 64):  # chunk by chunk
        ...     sm.forward(z[a:a + 64], free[a:a + 64], np.arange(a, min(a + 64, 300)) * 0.01)
        >>> sm.smooth()
        >>> off, scale = sm.offsets(150, 151)
        >>> bool(np.allclose(off, smooth_bias(z, free, time_constant=0.2).offset[150]))
        True
    """

    def __init__(
        self,
        sensors: int,
        *,
        time_constant: float = DEFAULT_TIME_CONSTANT,
        period: float = 0.01,
        ft_std: Any = None,
        ft_cov: Any = None,
        offset: Any = None,
        prior_scale: float = 1e4,
        store: str | Any | None = None,
    ) -> None:
        S = self.S = int(sensors)
        self.R = _noise_cov(S, ft_std, ft_cov)
        self.period = float(period)
        self.q_rate = process_noise(time_constant, self.period) / self.period  # per s
        if not prior_scale > 0:
            raise InputError(f"prior_scale must be > 0, got {prior_scale!r}")
        x0 = np.zeros((S, 6)) if offset is None else np.asarray(offset, np.float64)
        if x0.size != S * 6 or not np.isfinite(x0).all():
            raise InputError(f"offset must be ({S}, 6) finite [N; N m], got {np.shape(offset)}")
        self._x = x0.reshape(S, 6).copy()
        self._p = np.full(S, float(prior_scale))
        self._t: float | None = None
        self.frames = 0
        self.width = 6 * S + 2 * S  # per frame: x_filt (S, 6), p_filt (S,), p_pred (S,)
        self.path = None if store is None else str(store)
        self._file = None if store is None else open(self.path, "wb")  # noqa: SIM115
        self._parts: list[np.ndarray] = []
        self._mem: np.ndarray | None = None  # (N, width) after smooth(), without a file
        self._smoothed = False

    def forward(self, z: Any, free: Any, t: Any = None) -> None:
        """Filter the next frames (the tracker's update, without innovation gate).

        Args:
            z: ``(n, S, 6)`` residuals ``ft - ft_model`` [N; N m] (non-finite: not measured).
            free: ``(n, S)`` or ``(n,)`` bool, the frames that may measure each offset.
            t: ``(n,)`` time stamps, s, not decreasing across chunks (None: ``period`` apart).

        Raises:
            InputError: shapes, decreasing time stamps, or after :meth:`smooth`.
        """
        if self._smoothed:
            raise InputError("BiasSmoother.forward after smooth()")
        S = self.S
        z = np.asarray(z, np.float64).reshape(-1, S, 6)
        n = z.shape[0]
        free = np.asarray(free, bool)
        if free.shape == (n,):
            free = np.broadcast_to(free[:, None], (n, S))
        if free.shape != (n, S):
            raise InputError(f"contact_free must be ({n},) or ({n}, {S}), got {free.shape}")
        free = free & np.isfinite(z).all(-1)
        if t is None:
            ts = (0.0 if self._t is None else self._t) + self.period * np.arange(
                0 if self._t is None else 1, n + (0 if self._t is None else 1)
            )
        else:
            ts = np.asarray(t, np.float64).reshape(-1)
            if ts.shape != (n,) or not np.isfinite(ts).all():
                raise InputError(f"t must be ({n},) finite time stamps in s")
        dt = np.diff(ts, prepend=ts[:1] if self._t is None else self._t)
        if (dt < 0).any():
            raise InputError("time stamps must not decrease")
        if n:
            self._t = float(ts[-1])
        q = self.q_rate * dt
        out = np.empty((n, self.width))
        xs = out[:, : 6 * S].reshape(n, S, 6)
        p_filt, p_pred = out[:, 6 * S : 7 * S], out[:, 7 * S :]
        # the variances and gains: they depend only on the gating and the steps (a scalar
        # recursion per sensor, on Python floats: the same arithmetic as numpy's, without its
        # per-call cost)
        gain = np.zeros((n, S))
        ql = q.tolist()
        for s in range(S):
            p, fr = float(self._p[s]), free[:, s].tolist()
            pp, pf, gs = [0.0] * n, [0.0] * n, [0.0] * n
            for k in range(n):
                p = p + ql[k]
                pp[k] = p
                g = p / (p + 1.0) if fr[k] else 0.0
                gs[k] = g
                p = p * (1.0 - g)
                pf[k] = p
            self._p[s] = p
            p_pred[:, s], p_filt[:, s], gain[:, s] = pp, pf, gs
        # the offsets: x_k = (1 - g_k) x_{k-1} + g_k z_k, a linear recurrence whose coefficients
        # are known now: all frames at once by an affine scan
        zf = np.where(free[..., None], z, 0.0)
        A, B = _affine_scan((1.0 - gain)[..., None], gain[..., None] * zf)
        xs[...] = A * self._x + B
        x = xs[-1].copy() if n else self._x
        self._x = x
        self.frames += n
        if self._file is not None:
            self._file.write(out.tobytes())
        else:
            self._parts.append(out)

    def smooth(self, smoother: bool = True, block: int = 65536) -> None:
        """End the forward pass; with ``smoother`` run the Rauch-Tung-Striebel pass backward.

        Rauch, Tung and Striebel 1965 with the identity transition (``x_pred[k + 1] =
        x_filt[k]``): ``x_s[k] = x_f[k] + c_k (x_s[k + 1] - x_f[k])``, ``c_k = p_f[k] /
        p_pred[k + 1]``, ``p_s[k] = p_f[k] + c_k^2 (p_s[k + 1] - p_pred[k + 1])``, block by block
        from the end, each block read from the store, smoothed and written back in place
        (``block`` frames in memory at a time when the states are in a file).
        """
        if self._smoothed:
            return
        self._smoothed = True
        S, N = self.S, self.frames
        if self._file is not None:
            self._file.close()
            self._file = None
        else:
            self._mem = np.concatenate(self._parts) if self._parts else np.zeros((0, self.width))
            self._parts = []
        if not smoother or N < 2:
            return
        # carried across blocks: frame k + 1's smoothed state and predicted variance
        last = self._read(N - 1, N)[0]
        x_next = last[: 6 * S].reshape(S, 6).copy()
        p_next, pp_next = last[6 * S : 7 * S].copy(), last[7 * S :].copy()
        end = N - 1
        while end > 0:
            lo = max(0, end - block)
            blk = self._read(lo, end)  # frames lo .. end - 1
            xb = blk[:, : 6 * S].reshape(-1, S, 6)
            pf, pp = blk[:, 6 * S : 7 * S], blk[:, 7 * S :]
            # x_s[k] = (1 - c_k) x_f[k] + c_k x_s[k + 1] and p_s[k] = c_k^2 p_s[k + 1] + p_f[k]
            # - c_k^2 p_pred[k + 1]: linear recurrences backward, all frames of the block at
            # once (affine scans from the block's end)
            ppn = np.concatenate([pp[1:], pp_next[None]])  # frame k + 1's predicted variance
            c = pf / ppn
            A, B = _affine_scan(c[::-1, :, None], ((1.0 - c)[..., None] * xb)[::-1])
            xb[...] = (A * x_next + B)[::-1]
            x_next = xb[0].copy()
            c2 = c * c
            A, B = _affine_scan(c2[::-1], (pf - c2 * ppn)[::-1])
            pf[...] = (A * p_next + B)[::-1]
            p_next = pf[0].copy()
            pp_next = pp[0].copy()
            self._write(lo, blk)
            end = lo

    def _read(self, lo: int, hi: int) -> np.ndarray:
        """``(hi - lo, width)`` stored states (a copy)."""
        hi = min(hi, self.frames)
        if hi <= lo:
            return np.zeros((0, self.width))
        if self._mem is not None:
            return self._mem[lo:hi].copy()
        count, offset = (hi - lo) * self.width, lo * self.width * 8
        return np.fromfile(self.path, np.float64, count, offset=offset).reshape(-1, self.width)

    def _write(self, lo: int, blk: np.ndarray) -> None:
        if self._mem is not None:
            self._mem[lo : lo + len(blk)] = blk
            return
        with open(self.path, "r+b") as f:  # type: ignore[arg-type]
            f.seek(lo * self.width * 8)
            f.write(np.ascontiguousarray(blk, np.float64).tobytes())

    def offsets(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Frames ``lo .. hi - 1`` after :meth:`smooth`: ``offset (n, S, 6)``, ``scale (n, S)``.

        ``scale`` is the variance in units of ``R`` (the component standard deviations are
        ``sqrt(scale * diag(R))``, :meth:`std`). Read from the store: memory stays ``hi - lo``
        frames.
        """
        if not self._smoothed:
            raise InputError("BiasSmoother.offsets before smooth()")
        S = self.S
        blk = self._read(lo, hi)
        return blk[:, : 6 * S].reshape(-1, S, 6), blk[:, 6 * S : 7 * S]

    def std(self, scale: np.ndarray) -> np.ndarray:
        """``(n, S, 6)`` standard deviations [N; N m] from :meth:`offsets`' ``scale``."""
        return np.sqrt(scale[..., None] * np.diagonal(self.R, axis1=-2, axis2=-1))

    def close(self) -> None:
        """Release the store (the file itself is the caller's to delete)."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self._mem = None
        self._parts = []


def smooth_bias(
    residual: Any,
    contact_free: Any,
    t: Any = None,
    *,
    time_constant: float = DEFAULT_TIME_CONSTANT,
    period: float | None = None,
    ft_std: Any = None,
    ft_cov: Any = None,
    offset: Any = None,
    prior_scale: float = 1e4,
    smoother: bool = True,
) -> BiasTrack:
    """The offsets of a whole log: the tracker's filter forward, then the RTS smoother backward.

    With ``smoother=False`` this is exactly :class:`BiasTracker` run frame by frame (without
    innovation gate): each frame's offset from the frames up to it. With the smoother each frame
    gets the estimate from the whole log, so the frames of a contact get the offset interpolated
    between the contact-free frames before and after it. In memory; :class:`BiasSmoother` (which
    this runs) takes a log chunk by chunk.

    Args:
        residual: ``(N, S, 6)`` or ``(N, 6)`` ``ft - ft_model`` ``[N; N m]`` per frame.
        contact_free: ``(N,)`` or ``(N, S)`` bool: frames that may measure the offset.
        t: ``(N,)`` time stamps, s (default ``period`` apart).
        time_constant: s, as :class:`BiasTracker`.
        period: nominal period, s (default: the median step of ``t``, else 0.01).
        ft_std: as :class:`BiasTracker`.
        ft_cov: as :class:`BiasTracker`.
        offset: ``(S, 6)`` prior offset before the first frame (default zeros).
        prior_scale: its covariance in units of ``R``.
        smoother: run the backward pass.

    Returns:
        :class:`BiasTrack` (``(N, S, ...)`` arrays, ``S = 1`` for a ``(N, 6)`` input).

    Raises:
        InputError: inconsistent shapes, decreasing time stamps.

    Example:
        >>> import numpy as np
        >>> z = np.zeros((300, 6)); z[:, 0] = np.linspace(0.0, 3.0, 300)  # a drifting fx offset
        >>> free = np.ones(300, bool); free[100:200] = False  # a contact in the middle
        >>> tr = smooth_bias(z, free, time_constant=0.2)
        >>> bool(abs(tr.offset[150, 0, 0] - z[150, 0]) < 0.01)  # interpolated across it
        True
    """
    z = np.asarray(residual, dtype=np.float64)
    if z.ndim == 2:
        z = z[:, None, :]
    if z.ndim != 3 or z.shape[-1] != 6:
        raise InputError(f"residual must be (N, S, 6) or (N, 6), got {np.shape(residual)}")
    N, S, _ = z.shape
    free = np.asarray(contact_free, dtype=bool)
    if free.shape == (N,):
        free = np.broadcast_to(free[:, None], (N, S))
    if free.shape != (N, S):
        raise InputError(f"contact_free must be ({N},) or ({N}, {S}), got {free.shape}")
    free = free & np.isfinite(z).all(-1)
    if t is None:
        period = 0.01 if period is None else float(period)
        ts = None
        dt = np.full(N, period)
    else:
        ts = np.asarray(t, dtype=np.float64).reshape(-1)
        if ts.shape != (N,) or not np.isfinite(ts).all():
            raise InputError(f"t must be ({N},) finite time stamps in s")
        dt = np.diff(ts, prepend=ts[:1])
        if (dt < 0).any():
            raise InputError("time stamps must not decrease")
        if period is None:
            period = float(np.median(dt[1:])) if N > 1 and np.median(dt[1:]) > 0 else 0.01
    if N:
        dt[0] = 0.0
    sm = BiasSmoother(S, time_constant=time_constant, period=float(period), ft_std=ft_std,
                      ft_cov=ft_cov, offset=offset, prior_scale=prior_scale)  # fmt: skip
    sm.forward(z, free, ts)
    sm.smooth(smoother)
    x, p = sm.offsets(0, N)
    since = np.empty((N, S))
    last = np.full(S, np.inf)
    for k in range(N):
        last = np.where(free[k], 0.0, last + dt[k])
        since[k] = last
    return BiasTrack(x, p, sm.R, free, since)
