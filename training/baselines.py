"""Physics layers of a correction: nominal prediction, constant offset, inertial re-identification.

The contact-free reading of a sensor is ``Y(q, qd, qdd) theta`` (:func:`sensor_regressor
<torchcontact.residual.sensor_regressor>`, ten parameters per body the sensor carries). With an
offset ``o`` and parameter errors ``delta`` the residual of the nominal model is
``r = [I | Y] (o, delta) + noise``: a linear least-squares problem over the contact-free frames.

Not every combination of parameters changes the reading (a fixed-base sensor cannot tell a mass
on its z axis from an ``fz`` offset; a trajectory may not excite some inertia products), so the
fit works in a base of the *identifiable* space: the stacked design matrix is reduced per time
block by QR (memory flat in the log length), the blocks' factors are stacked and reduced again,
and the column-scaled factor's SVD gives the directions ordered by how much the data excite them.
Directions below ``rcond`` of the largest singular value are never fitted; among the others the
truncation rank is chosen on the validation blocks (truncated SVD), so weakly excited directions
are fitted only where that lowers the error on unseen blocks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

import torchcontact as tc
from torchcontact.residual import sensor_regressor, subtree_bodies

from .data import ResidualDataset


def no_contacts(n: int, dtype=torch.float64) -> tc.Contacts:
    """Zero contact slots for ``n`` frames (the contact-free prediction)."""
    return tc.Contacts((), (), torch.zeros(n, 0, 3, dtype=dtype))


def predict_free(
    model: tc.RobotModel, sensor: str, q, qd, qdd, usable=None, chunk: int = 32768
) -> np.ndarray:
    """Contact-free reading ``(N, 6)`` the model predicts (:meth:`ContactEstimator.predict_ft`).

    Frames not ``usable`` (non-finite joint values) get NaN.
    """
    est = tc.ContactEstimator(model, [sensor])
    n = len(q)
    usable = np.ones(n, bool) if usable is None else np.asarray(usable, bool)
    out = np.full((n, 6), np.nan)
    idx = np.flatnonzero(usable)
    for s in range(0, len(idx), chunk):
        sel = idx[s : s + chunk]
        t = [torch.as_tensor(np.asarray(x)[sel], dtype=model.dtype) for x in (q, qd, qdd)]
        out[sel] = est.predict_ft(*t, no_contacts(len(sel), model.dtype))[sensor].numpy()
    return out


def fit_offset(residual: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Constant offset ``(6,)``: the mean residual of ``frames`` (contact-free, usable)."""
    if not len(frames):
        raise ValueError("no contact-free frame to fit the offset on")
    return residual[frames].mean(0)


def _qr_rhs(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R`` and ``Q^T b`` of the reduced QR ``A = Q R``.

    By torch's LAPACK, which follows ``torch.set_num_threads``: numpy's multithreaded OpenBLAS
    was 170x slower on a loaded 2-core machine (1.1 s for a 3000 x 56 QR).
    """
    Q, R = torch.linalg.qr(torch.as_tensor(A))
    return R.numpy(), (Q.T @ torch.as_tensor(b)).numpy()


@dataclass
class RegressorBlocks:
    """Per time block, the QR reduction of the physics least squares ``[I | Y] x = r``.

    ``||A_b x - r_b||^2 = ||R_b x - c_b||^2 + (rr_b - ||c_b||^2)`` for block ``b``'s frames, so
    any union of blocks is solved from the stacked ``R_b``, ``c_b`` alone.

    Attributes:
        blocks: the ``(start, stop)`` frame ranges.
        R: ``(nblocks, C, C)`` upper-triangular factors, ``C = 6 + P``.
        c: ``(nblocks, C)`` ``Q_b^T r_b``.
        rr: ``(nblocks,)`` ``||r_b||^2``.
        rows: ``(nblocks,)`` frames used per block.
        bodies: body indices of the ``P / 10`` parameter groups.
    """

    blocks: list[tuple[int, int]]
    R: np.ndarray
    c: np.ndarray
    rr: np.ndarray
    rows: np.ndarray
    bodies: list[int] = field(default_factory=list)

    @classmethod
    def build(
        cls,
        model: tc.RobotModel,
        ds: ResidualDataset,
        residual: np.ndarray,
        blocks: Sequence[tuple[int, int]],
        chunk: int = 16384,
    ) -> RegressorBlocks:
        """Reduce every block's contact-free, usable frames (regressor by the library).

        The regressor is computed for up to ``chunk`` frames at a time.
        """
        bodies = subtree_bodies(model, ds.sensor)
        C = 6 + 10 * len(bodies)
        nb = len(blocks)
        R = np.zeros((nb, C, C))
        c = np.zeros((nb, C))
        rr = np.zeros(nb)
        rows = np.zeros(nb, np.int64)
        targets = ds.targets
        sels = [np.arange(s, e)[targets[s:e]] for s, e in blocks]
        i = 0
        while i < nb:  # the regressor of several blocks at once (fewer, larger batches)
            j, n = i, 0
            while j < nb and (j == i or n + len(sels[j]) <= chunk):
                n += len(sels[j])
                j += 1
            sel = np.concatenate(sels[i:j])
            if len(sel):
                t = [torch.as_tensor(x[sel], dtype=model.dtype) for x in (ds.q, ds.qd, ds.qdd)]
                Y = sensor_regressor(model, ds.sensor, *t, bodies).numpy()  # (n, 6, P)
            at = 0
            for k in range(i, j):  # then each block's QR
                m = len(sels[k])
                rows[k] = m
                if m:
                    Yk = Y[at : at + m]
                    A = np.concatenate([np.broadcast_to(np.eye(6), (m, 6, 6)), Yk], -1)
                    r = residual[sels[k]].reshape(-1)
                    Rb, cb = _qr_rhs(A.reshape(m * 6, C), r)
                    R[k, : Rb.shape[0]] = Rb
                    c[k, : Rb.shape[0]] = cb
                    rr[k] = r @ r
                at += m
            i = j
        return cls(list(blocks), R, c, rr, rows, bodies)

    def combine(self, ids: Sequence[int]) -> tuple[np.ndarray, np.ndarray, float, int]:
        """``(R, c, rr, rows)`` of the union of blocks ``ids`` (a second QR of the stack)."""
        ids = [i for i in ids if self.rows[i] > 0]
        C = self.R.shape[-1]
        if not ids:
            return np.zeros((C, C)), np.zeros(C), 0.0, 0
        R, c = _qr_rhs(self.R[ids].reshape(-1, C), self.c[ids].reshape(-1))
        Rf = np.zeros((C, C))
        cf = np.zeros(C)
        Rf[: R.shape[0]], cf[: R.shape[0]] = R, c
        return Rf, cf, float(self.rr[ids].sum()), int(self.rows[ids].sum())


@dataclass
class InertialFit:
    """Offset plus inertial parameter change fitted in the identifiable directions.

    Attributes:
        offset: ``(6,)`` [N; N m].
        delta: ``(P,)`` parameter change, :data:`torchcontact.residual.PARAM_NAMES` per body.
        bodies: body indices.
        rank: directions fitted (chosen on the validation blocks).
        identifiable: directions above ``rcond`` (never more are fitted).
        columns: ``6 + P`` unknowns.
        singular_values: of the column-scaled design matrix, descending.
        val_rms: validation RMS residual per candidate rank ``0 .. identifiable``.
    """

    offset: np.ndarray
    delta: np.ndarray
    bodies: list[int]
    rank: int
    identifiable: int
    columns: int
    singular_values: np.ndarray
    val_rms: np.ndarray

    def info(self) -> dict:
        """JSON-ready summary (recorded in the checkpoint)."""
        return {
            "rank": self.rank,
            "identifiable": self.identifiable,
            "unknowns": self.columns,
            "singular_values": [float(s) for s in self.singular_values],
            "note": "offset and parameter changes fitted in the rank leading directions of the"
            " column-scaled regressor's SVD; the other directions stay at the nominal values",
        }


def fit_inertial(
    rb: RegressorBlocks,
    train: Sequence[int],
    val: Sequence[int],
    rcond: float = 1e-7,
    rank: int | None = None,
) -> InertialFit:
    """Fit offset + parameter change on blocks ``train``, truncation rank chosen on ``val``.

    Args:
        rb: the reduced blocks.
        train: indices into ``rb.blocks`` to fit on.
        val: indices to choose the rank on (empty: the largest identifiable rank).
        rcond: relative singular-value threshold of identifiability.
        rank: a fixed rank instead of the validation choice (clipped to the identifiable one).

    Returns:
        :class:`InertialFit`.
    """
    R, c, _, rows = rb.combine(train)
    if rows == 0:
        raise ValueError("no contact-free frame in the training blocks")
    scale = np.sqrt((R**2).sum(0))  # column norms of the stacked design matrix
    scale[scale == 0] = 1.0
    U, s, Vt = (x.numpy() for x in torch.linalg.svd(torch.as_tensor(R / scale)))
    k_max = int((s > rcond * s[0]).sum()) if s[0] > 0 else 0
    z = U.T @ c
    # solution of rank k: x_k = D^-1 V_k (z_k / s_k); candidates as cumulative sums
    steps = (Vt[:k_max].T * (z[:k_max] / s[:k_max])) / scale[:, None]  # (C, k_max)
    X = np.concatenate([np.zeros((len(scale), 1)), np.cumsum(steps, 1)], 1)  # (C, k_max + 1)
    Rv, cv, rrv, nv = rb.combine(val)
    if nv:
        RX = (torch.as_tensor(Rv) @ torch.as_tensor(X)).numpy()  # torch: see _qr_rhs
        rss = (RX**2).sum(0) - 2 * (cv[:, None] * RX).sum(0) + rrv
        val_rms = np.sqrt(np.maximum(rss, 0) / (6 * nv))
    else:
        val_rms = np.full(k_max + 1, np.nan)
    if rank is not None:
        k = min(int(rank), k_max)
    elif nv:
        k = int(np.argmin(val_rms))
    else:
        k = k_max
    x = X[:, k]
    return InertialFit(
        offset=x[:6],
        delta=x[6:],
        bodies=list(rb.bodies),
        rank=k,
        identifiable=k_max,
        columns=len(scale),
        singular_values=s,
        val_rms=val_rms,
    )
