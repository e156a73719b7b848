"""The F/T noise a log's solve is weighted by (``estimate --ft-noise``, ``--unweighted``).

The estimator whitens each sensor's rows by its reading noise covariance (the weighted solve of
:func:`torchcontact.solve.weighted_solve_program`, ``docs/accuracy.md``). A log run takes each
sensor's noise from the first of these that gives it:

1. ``--ft-noise SENSOR=SIGMA_F,SIGMA_M`` (or 6 standard deviations, or a driver profile name):
   ``ft_noise`` of :func:`~torchcontact.logs.estimate_file`;
2. the log's ``ft_cov.<sensor>`` column, one covariance per frame
   (:func:`torchcontact.logs.format.ft_cov_column`);
3. the datasheet ``[noise]`` of the sensor's driver profile named in the log's metadata
   (:data:`torchcontact.logs.format.META_FT_PROFILES`);
4. an estimate from the log's contact-free frames (:func:`contact_free_noise`).

When a sensor gets none (too few contact-free frames, or no measurable noise in them), or the
log has ``tau_measured`` (the torque rows' noise is not known), the run keeps the paper's
unweighted ``pinv(A) b`` and says why; ``--unweighted`` asks for it. The summary's ``noise``
says which source each sensor used.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from torchcontact.errors import InputError
from torchcontact.noise import (  # the one parser and value types, re-exported here
    FTNoise,
    SensorNoise,
    fixed_noise,
    parse_ft_noise,
    profile_std,
)

__all__ = [
    "MIN_NOISE_PAIRS",
    "NOISE_PAIRS",
    "STD_FLOOR",
    "FTNoise",
    "SensorNoise",
    "contact_free_noise",
    "fixed_noise",
    "parse_ft_noise",
]

#: Consecutive contact-free frame pairs a sensor needs for a noise estimate (fewer: unweighted).
MIN_NOISE_PAIRS = 50
#: Contact-free frame pairs the estimate reads at most (the first ones of the log).
NOISE_PAIRS = 20_000
#: Smallest standard deviation an estimate returns, N or N m; a sensor whose estimate has an axis
#: at this floor (a noise-free simulated log, a quantised reading that repeats) is not weighted by
#: it: the run is unweighted and says why, instead of whitening by rounding errors.
STD_FLOOR = 1e-6
#: MAD -> standard deviation of a Gaussian.
_MAD_SCALE = 1.482602218505602


def resolve(
    sensors: Sequence[str],
    robot_sensors: Sequence[str],
    given: Mapping[str, tuple[float, ...] | str] | None,
    columns: Sequence[str],
    metadata: Mapping[bytes, bytes] | None,
    estimate: Any,
    *,
    unweighted: bool = False,
    torques: bool = False,
    source: str = "",
) -> FTNoise:
    """Each sensor's noise from the first source that gives it (see the module).

    Args:
        sensors: the sensors in use.
        robot_sensors: every F/T sensor of the robot.
        given: parsed ``--ft-noise`` (:func:`parse_ft_noise`), or None.
        columns: the log's column names.
        metadata: the log's schema metadata.
        estimate: ``f(sensors) -> {sensor: ((6,) std, pairs)}`` for the sensors left
            (:func:`contact_free_noise` over the log's first chunks); called only when needed.
        unweighted: ``--unweighted``: the paper's ``pinv(A) b``.
        torques: the log has ``tau_measured``.
        source: the log's name, for messages.

    Raises:
        InputError: ``--ft-noise`` for a sensor the robot does not have or the run does not use,
            an unknown profile or one without noise, ``--ft-noise`` with ``unweighted``.
    """
    from torchcontact.logs.format import META_FT_PROFILES, ft_cov_column

    given = dict(given or {})
    for s in given:
        if s not in robot_sensors:
            raise InputError(
                f"--ft-noise {s}: the robot has no F/T sensor {s!r} (its sensors:"
                f" {list(robot_sensors)})"
            )
        if s not in sensors:
            raise InputError(f"--ft-noise {s}: not a sensor in use ({list(sensors)})")
    if unweighted:
        if given:
            raise InputError("give --ft-noise or --unweighted, not both")
        return FTNoise({}, "--unweighted")
    if torques:
        return FTNoise({}, "the log has tau_measured, whose noise is not known")
    profiles: dict[str, str] = {}
    raw = (metadata or {}).get(META_FT_PROFILES)
    if raw:
        try:
            profiles = dict(json.loads(raw))
        except (ValueError, TypeError):
            profiles = {}
    out: dict[str, SensorNoise] = {}
    for s in sensors:
        if s in given:
            g = given[s]
            if isinstance(g, str):
                out[s] = SensorNoise(f"profile {g} (--ft-noise)", profile_std(g, f"--ft-noise {s}"))
            else:
                out[s] = SensorNoise("--ft-noise", tuple(g))
        elif ft_cov_column(s) in columns:
            out[s] = SensorNoise(f"column {ft_cov_column(s)}")
        elif s in profiles:
            where = f"{source}: metadata {META_FT_PROFILES.decode()} {s}"
            name = str(profiles[s])
            out[s] = SensorNoise(f"profile {name} (log metadata)", profile_std(name, where))
    left = [s for s in sensors if s not in out]
    if left:
        found = estimate(left)
        for s in left:
            std, pairs = found[s]
            if pairs < MIN_NOISE_PAIRS:
                return FTNoise(
                    out,
                    f"{s}: {pairs} consecutive contact-free frame pairs, fewer than the"
                    f" {MIN_NOISE_PAIRS} a noise estimate needs; give --ft-noise",
                )
            if (np.asarray(std) <= STD_FLOOR).any():
                return FTNoise(
                    out,
                    f"{s}: its contact-free frames show no noise (std <= {STD_FLOOR:g} on an"
                    " axis: a noise-free or quantised log); give --ft-noise",
                )
            out[s] = SensorNoise(f"contact-free frames ({pairs} pairs)", tuple(std))
    return FTNoise(out)


def _median(x: np.ndarray) -> np.ndarray:
    """``np.median(x, 0)`` of finite values: the same numbers.

    Without numpy's import of ``numpy.ma`` (15 ms of a log run's start).
    """
    n = len(x)
    k = (n - 1) // 2
    part = np.partition(x, [k, n // 2], axis=0)
    return part[k] if n % 2 else (part[k] + part[n // 2]) / 2.0


def contact_free_noise(
    le: Any, chunks: Iterable[Any], sensors: Sequence[str], pairs: int = NOISE_PAIRS
) -> dict[str, tuple[np.ndarray, int]]:
    """Each sensor's reading noise from the log's contact-free frames.

    On frames without a contact record (and nothing wrong with them), ``r = ft - ft_model(q, qd,
    qdd)`` is the reading minus the contact-free prediction. Its change between consecutive
    frames of one time segment, ``r[t+1] - r[t]``, has variance ``2 sigma^2`` for white noise,
    while offsets, drift and the smooth model errors along a trajectory cancel; ``sigma`` per
    axis is its median absolute deviation (``1.4826 MAD / sqrt(2)``, robust to the odd jump),
    at least :data:`STD_FLOOR`. A diagonal covariance: the axes' correlations are not estimated.

    Args:
        le: the log's :class:`~torchcontact.logs.LogEstimator`.
        chunks: decoded chunks (:func:`~torchcontact.logs.chunks.decoded_chunks`) from the log's
            start; read until ``pairs`` pairs are found.
        sensors: the sensors to estimate.
        pairs: pairs to use at most.

    Returns:
        sensor -> ``((6,) std [N; N m], pairs used)``.
    """
    import torch

    from torchcontact.contacts import Contacts

    model, est = le.model, le.estimator
    diffs: list[np.ndarray] = []
    have = 0
    for d in chunks:
        free = d.issues.code == 0
        if len(d.records):
            free[d.records.frame] = False
        for x in (d.q, d.qd, d.qdd, *d.ft.values(), *d.base.values()):
            free &= np.isfinite(x).all(1)
        nxt = free[1:] & free[:-1]
        if d.starts is not None:
            nxt &= ~d.starts[1:]
        if not nxt.any():
            continue
        rows = np.flatnonzero(free)
        t = {k: torch.as_tensor(v[rows], dtype=model.dtype) for k, v in
             (("q", d.q), ("qd", d.qd), ("qdd", d.qdd))}  # fmt: skip
        none = Contacts([], [], torch.zeros(len(rows), 0, 3, dtype=model.dtype))
        kw = {}
        if d.base:
            from torchcontact.dynamics import BaseMotion

            kw["base"] = BaseMotion(*(torch.as_tensor(d.base[k][rows], dtype=model.dtype)
                                      for k in ("omega", "domega", "proper_acc")))  # fmt: skip
        # the kernel only if built already, else the tape VM: a build of its own would hold the
        # compile slot the run's estimator kernel needs next (a first run would wait for two
        # builds in a row); its kernel builds once the process exits, for later runs
        pred = est.predict_ft(t["q"], t["qd"], t["qdd"], none, backend="cached", **kw)
        r = np.full((d.n, 6 * len(sensors)), np.nan)
        r[rows] = np.concatenate(
            [d.ft[s][rows] - pred[s].detach().cpu().numpy() for s in sensors], 1
        )
        fin = np.isfinite(r).all(1)  # a state that overflows the dynamics is no sample
        nxt &= fin[1:] & fin[:-1]
        diffs.append((r[1:] - r[:-1])[nxt])
        have += int(nxt.sum())
        if have >= pairs:
            break
    if not diffs:
        return {s: (np.full(6, np.nan), 0) for s in sensors}
    dr = np.concatenate(diffs)[:pairs]
    mad = _median(np.abs(dr - _median(dr)))
    std = np.maximum(_MAD_SCALE * mad / math.sqrt(2.0), STD_FLOOR)
    return {s: (std[6 * i : 6 * i + 6], len(dr)) for i, s in enumerate(sensors)}
