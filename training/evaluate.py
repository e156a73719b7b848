"""Scores of corrections: what they leave on contact-free frames, and contact-force errors.

On a recorded log there is no ground truth: a correction is scored by the F/T residual it
leaves on held-out contact-free frames, per axis (:func:`residual_rmse`). Simulated logs also
carry the true contacts, and :func:`contact_metrics` estimates them from the corrected readings.
"""

from __future__ import annotations

import numpy as np
import torch

import torchcontact as tc


def _rmse(err: np.ndarray) -> float:
    """Root mean square of the vector norm over frames (NaN when there are none)."""
    return float(np.sqrt(np.mean(np.sum(err**2, -1)))) if len(err) else float("nan")


def contact_metrics(
    est: tc.ContactEstimator,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    ft: np.ndarray,
    truth: dict,
    sensor: str,
) -> dict[str, float]:
    """Estimate the contacts from ``ft`` (already corrected) and compare with the truth.

    Slots: one per (contact index k, skin link), active where the truth has contact k on that
    link, at the true position. ``force`` slots (3 unknowns each) give the force errors; on
    one-contact frames (identifiable: rank 3 of 3) and two-contact frames (rank-deficient, the
    minimum-norm solution; Del Prete et al. 2012). ``wrench`` slots on one-contact frames (6
    unknowns, 6 equations) give the moment error (the true moment about the point is zero).

    Args:
        est: the estimator.
        q: ``(n, nv)`` frames to evaluate; ``qd``, ``qdd`` likewise.
        qd: ``(n, nv)``.
        qdd: ``(n, nv)``.
        ft: ``(n, 6)`` corrected readings.
        truth: ``contact_link (n, K)``, ``contact_position (n, K, 3)``, ``contact_force
            (n, K, 3)``, ``links``.
        sensor: the sensor name.

    Returns:
        ``force_rmse`` (N), ``moment_rmse`` (N m), ``force_rmse_2c`` (N), frame counts.
    """
    link_idx, pos, force = truth["contact_link"], truth["contact_position"], truth["contact_force"]
    links = truth["links"]
    n, K = link_idx.shape
    L = len(links)
    slot_links = tuple(links[li] for _ in range(K) for li in range(L))
    active = np.stack([link_idx[:, k] == li for k in range(K) for li in range(L)], 1)
    positions = np.repeat(pos, L, axis=1)
    ncontacts = (link_idx >= 0).sum(1)
    out: dict[str, float] = {}
    f64 = torch.float64

    def run(kinds, sel):
        c = tc.Contacts(
            slot_links,
            (kinds,) * len(slot_links),
            torch.as_tensor(positions[sel], dtype=f64),
            active=torch.as_tensor(active[sel]),
        )
        e = est.estimate(
            *(torch.as_tensor(x[sel], dtype=f64) for x in (q, qd, qdd)),
            ft={sensor: torch.as_tensor(ft[sel], dtype=f64)},
            contacts=c,
        )
        # the estimate of the slot that holds contact k: slot k * L + link
        f_hat = np.zeros((int(sel.sum()), K, 3))
        m_hat = np.zeros((int(sel.sum()), K, 3))
        F, M = e.force.numpy(), e.moment.numpy()
        for k in range(K):
            li = np.clip(link_idx[sel, k], 0, None)
            f_hat[:, k] = F[np.arange(len(li)), k * L + li]
            m_hat[:, k] = M[np.arange(len(li)), k * L + li]
        return f_hat, m_hat

    one, two = ncontacts == 1, ncontacts == 2
    if one.any():
        f_hat, _ = run("force", one)
        on = link_idx[one] >= 0
        out["force_rmse"] = _rmse((f_hat - force[one])[on])
        f_hat, m_hat = run("wrench", one)
        out["moment_rmse"] = _rmse(m_hat[on])
        out["force_rmse_wrench_slot"] = _rmse((f_hat - force[one])[on])
    if two.any():
        f_hat, _ = run("force", two)
        on = link_idx[two] >= 0
        out["force_rmse_2c"] = _rmse((f_hat - force[two])[on])
    out["frames_1c"] = int(one.sum())
    out["frames_2c"] = int(two.sum())
    return out


AXES = ("fx", "fy", "fz", "mx", "my", "mz")


def residual_rmse(residual: np.ndarray) -> dict[str, float]:
    """RMS of what a correction leaves on contact-free frames ``(n, 6)``: per axis and in norm.

    Returns:
        ``rms.fx`` .. ``rms.mz`` (N, N m), ``residual_force_rms`` and ``residual_moment_rms``
        (root mean square of the force and moment vector norms), ``frames_free``.
    """
    out = {f"rms.{a}": _rmse(residual[:, i : i + 1]) for i, a in enumerate(AXES)}
    out["residual_force_rms"] = _rmse(residual[:, :3])
    out["residual_moment_rms"] = _rmse(residual[:, 3:])
    out["frames_free"] = len(residual)
    return out
