"""Reference estimates of the cone benchmark in numpy: posterior mean, centre of the feasible set.

Both work on a frame's whitened contact matrix ``A~ = L^-1 A`` (6 rows, ``3 K`` columns of the
active pure forces, link frames) and reading ``b~ = L^-1 (reading - reading without contacts)``,
built column by column from ``ContactEstimator.predict_ft`` (``A`` is linear in the forces).

* :func:`posterior_mean`: the mean of ``p(x | b) ~ exp(-|A~ x - b~|^2 / 2) prod_k p(f_k)`` by
  random-walk Metropolis (Gaussian proposals shaped by ``A~^T A~ + I / F^2``, scale adapted to
  an acceptance of about 0.3 during burn-in), started from a given point of positive density:
  the Bayes estimate under the stated prior, the limit an estimator using that prior can reach.
* :func:`feasible_centre`: the analytic centre of the set of forces inside their cones, below a
  magnitude bound and consistent with the reading (``|A~ x - b~|^2 <= chi2``), by damped Newton
  steps on its log-barrier from an interior point.
"""

from __future__ import annotations

import math

import numpy as np
import torch

import torchcontact as tc


def contact_matrix(est, frames: dict) -> tuple[np.ndarray, np.ndarray]:
    """``A (n, 6, 3 K)`` and the contact-free reading ``r0 (n, 6)`` of the first sensor."""
    c = frames["contacts"]
    n, K = c.positions.shape[:2]
    q, qd, qdd = frames["q"], frames["qd"], frames["qdd"]
    s = est.sensor_names[0]

    def reading(w):
        known = tc.Contacts(c.links, ("known",) * K, c.positions, wrenches=w)
        return est.predict_ft(q, qd, qdd, known)[s].numpy()

    r0 = reading(torch.zeros(n, K, 6, dtype=torch.float64))
    A = np.zeros((n, 6, 3 * K))
    for k in range(K):
        for j in range(3):
            w = torch.zeros(n, K, 6, dtype=torch.float64)
            w[:, k, j] = 1.0
            A[:, :, 3 * k + j] = reading(w) - r0
    return A, r0


class ConePrior:
    """A density on each active force: direction within a band of angles from the inward
    normal (uniform over its solid angle), magnitude from a named distribution.

    Args:
        normals: ``(n, K, 3)`` outward unit normals.
        angles: ``(lo, hi)`` rad, the band of angles from ``-normal``.
        magnitude: ``("uniform", lo, hi)`` or ``("log", lo, hi)``, N.
    """

    def __init__(self, normals: np.ndarray, angles=(0.0, 0.5), magnitude=("uniform", 2.0, 20.0)):
        self.n = normals
        self.cos_lo, self.cos_hi = math.cos(angles[1]), math.cos(angles[0])
        self.kind, self.lo, self.hi = magnitude

    def log_density(self, f: np.ndarray, active: np.ndarray) -> np.ndarray:
        """``sum_k log p(f_k)`` over active slots, ``(n,)`` (-inf outside the support)."""
        r = np.linalg.norm(f, axis=-1)
        c = -(f * self.n).sum(-1) / np.maximum(r, 1e-300)
        ok = (c >= self.cos_lo) & (c <= self.cos_hi) & (r >= self.lo) & (r <= self.hi)
        # density in R^3: p_r(r) / (r^2 * solid angle); p_r ~ 1 (uniform) or ~ 1/r (log)
        lp = -2.0 * np.log(np.maximum(r, 1e-300))
        if self.kind == "log":
            lp = lp - np.log(np.maximum(r, 1e-300))
        lp = np.where(ok, lp, -np.inf)
        return np.where(active, lp, 0.0).sum(-1)

    def project(self, f: np.ndarray) -> np.ndarray:
        """``f`` moved into the support (direction to the band's middle if outside, magnitude
        clipped): a starting point of positive density."""
        r = np.linalg.norm(f, axis=-1, keepdims=True)
        u = f / np.maximum(r, 1e-12)
        c = -(u * self.n).sum(-1, keepdims=True)
        t = u + c * self.n
        t = t / np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), 1e-12)
        mid = 0.5 * (math.acos(self.cos_hi) + math.acos(self.cos_lo))
        inside = (c >= self.cos_lo) & (c <= self.cos_hi)
        u = np.where(inside, u, -math.cos(mid) * self.n + math.sin(mid) * t)
        return u * np.clip(r, self.lo * 1.01, self.hi * 0.99)


def posterior_mean(A, b, active, prior: ConePrior, x0, steps=20000, burn=8000, seed=0):
    """Posterior mean ``(n, 3 K)`` of the forces under ``prior`` (whitened ``A, b``).

    Args:
        A: ``(n, R, 3 K)`` whitened contact matrices.
        b: ``(n, R)`` whitened readings.
        active: ``(n, K)`` bool.
        prior: the density of each force.
        x0: ``(n, 3 K)`` starting points (moved into the prior's support).
        steps: Metropolis steps (the first ``burn`` adapt and are discarded).
        seed: random seed.

    Returns:
        ``(mean (n, 3 K), acceptance (n,))``.
    """
    rng = np.random.default_rng(seed)
    n, R, u = A.shape
    K = u // 3
    mask = np.repeat(active, 3, axis=1).astype(float)  # (n, u)
    H = np.einsum("nri,nrj->nij", A, A) + np.eye(u) / prior.hi**2
    H = H * mask[:, :, None] * mask[:, None, :] + np.eye(u) * (1 - mask)[:, :, None]
    Lp = np.linalg.cholesky(np.linalg.inv(H))  # proposal shape

    def logp(x):
        r = np.einsum("nri,ni->nr", A, x) - b
        return -0.5 * (r * r).sum(-1) + prior.log_density(x.reshape(n, K, 3), active)

    x = prior.project(x0.reshape(n, K, 3)).reshape(n, u) * mask
    lp = logp(x)
    scale = np.full(n, 2.38 / math.sqrt(max(u, 1)))
    total = np.zeros_like(x)
    acc = np.zeros(n)
    kept = 0
    for i in range(steps):
        prop = x + scale[:, None] * np.einsum("nij,nj->ni", Lp, rng.normal(size=(n, u))) * mask
        lq = logp(prop)
        take = np.log(rng.random(n)) < lq - lp
        x = np.where(take[:, None], prop, x)
        lp = np.where(take, lq, lp)
        if i < burn:  # adapt towards an acceptance of ~0.3
            scale *= np.where(take, 1.02, 0.99)
        else:
            total += x
            acc += take
            kept += 1
    return total / kept, acc / kept


def feasible_centre(A, b, active, C, F: float, chi2: float, x0, iters=60):
    """Analytic centre ``(n, 3 K)`` of {cones, |f_k| <= F, |A x - b|^2 <= chi2} (whitened).

    Args:
        A: ``(n, R, 3 K)``; b: ``(n, R)``; active: ``(n, K)``.
        C: ``(n, K, 3, 3)`` cone coordinates (``C f in Q^3``, as
            :func:`torchcontact.constrained.cone_rows`).
        F: magnitude bound, N.
        chi2: bound on the whitened residual's square.
        x0: ``(n, 3 K)`` strictly feasible starting points.
        iters: damped Newton steps.
    """
    n, R, u = A.shape
    K = u // 3
    act = np.repeat(active, 3, axis=1)
    J = np.diag([1.0, -1.0, -1.0])

    def barrier(x):
        f = x.reshape(n, K, 3)
        y = np.einsum("nkij,nkj->nki", C, f)
        cone = y[..., 0] ** 2 - y[..., 1] ** 2 - y[..., 2] ** 2
        mag = F**2 - (f * f).sum(-1)
        r = np.einsum("nri,ni->nr", A, x) - b
        fit = chi2 - (r * r).sum(-1)
        ok = ((cone > 0) & (y[..., 0] > 0) & (mag > 0) | ~active).all(-1) & (fit > 0)
        val = -(np.where(active, np.log(np.where(active, cone, 1.0))
                         + np.log(np.where(active, mag, 1.0)), 0.0)).sum(-1) - np.log(
            np.where(fit > 0, fit, 1.0))  # fmt: skip
        return np.where(ok, val, np.inf), y, cone, mag, r, fit

    x = x0.copy() * act
    for _ in range(iters):
        val, y, cone, mag, r, fit = barrier(x)
        f = x.reshape(n, K, 3)
        g = np.zeros((n, K, 3))
        H = np.zeros((n, u, u))
        for k in range(K):
            Ck = C[:, k]
            Jy = np.einsum("ij,nj->ni", J, y[:, k])
            gk = -2 * np.einsum("nji,nj->ni", Ck, Jy) / cone[:, k, None]
            gk += 2 * f[:, k] / mag[:, k, None]
            CJC = np.einsum("nai,ab,nbj->nij", Ck, J, Ck)
            gc = gk - 2 * f[:, k] / mag[:, k, None]  # the cone barrier's gradient
            Hk = -2 * CJC / cone[:, k, None, None] + np.einsum("ni,nj->nij", gc, gc)
            ff = np.einsum("ni,nj->nij", f[:, k], f[:, k])
            Hk += 2 * np.eye(3) / mag[:, k, None, None] + 4 * ff / mag[:, k, None, None] ** 2
            on = active[:, k, None, None]
            H[:, 3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = np.where(on, Hk, np.eye(3))
            g[:, k] = np.where(active[:, k, None], gk, 0.0)
        g = g.reshape(n, u)
        ATr = np.einsum("nri,nr->ni", A, r)
        g += 2 * ATr / fit[:, None]
        H += 2 * np.einsum("nri,nrj->nij", A, A) / fit[:, None, None]
        H += 4 * np.einsum("ni,nj->nij", ATr, ATr) / fit[:, None, None] ** 2
        H = H * act[:, :, None] * act[:, None, :] + np.eye(u) * (~act)[:, :, None]
        dx = -np.linalg.solve(H, (g * act)[..., None])[..., 0]
        lam = np.sqrt(np.maximum(-(g * dx).sum(-1), 0))
        t = 1.0 / (1.0 + lam)  # damped Newton: stays feasible for a self-concordant barrier
        x_new = x + t[:, None] * dx
        v_new = barrier(x_new)[0]
        x = np.where((v_new <= val)[:, None], x_new, x)
    return x
