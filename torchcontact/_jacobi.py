"""Exportable symmetric eigensolver: batched parallel cyclic Jacobi with a fixed sweep count.

ONNX has no SVD, eigendecomposition, inverse or solve, so the contact estimator's small Gram
matrix ``G = A A^T`` (6 x 6, or 6 + m with torque rows) is diagonalised here with plain elementwise
torch ops and constant indexing only; ``torch.onnx.export`` turns it into a straight-line graph.

**Algorithm** (Golub & Van Loan, *Matrix Computations*, 4th ed., Sec. 8.5.2 cyclic Jacobi and
8.5.4-8.5.5 the parallel "round-robin" ordering). A sweep visits every pair ``(p, q)`` once; the
pairs are grouped into ``n' - 1`` rounds of ``n'/2`` disjoint pairs (``n'`` = n rounded up to
even; a padding index is a no-op), and the rotations of one round commute, so each round is one
orthogonal ``J`` and ``A <- J^T A J``, ``V <- V J``. Each rotation is the symmetric Schur
rotation that zeroes ``a_pq`` (GVL Alg. 8.5.1), the angle ``|theta| <= pi/4`` with
``tan 2 theta = 2 a_pq / (a_qq - a_pp)`` taken as ``atan(...) / 2`` (``+-inf`` when
``a_pp = a_qq`` gives ``+-pi/4``; ``a_pq = 0`` no rotation), applied per index without forming
``J`` (fewer graph nodes than the ``t = sign(tau) / (|tau| + sqrt(1 + tau^2))`` form).

**Convergence.** Cyclic Jacobi converges quadratically once the off-diagonal norm is small
(Schonhage 1961; Wilkinson 1962: ``off(A_{k+1}) <= c off(A_k)^2 / delta`` with ``delta`` the
smallest gap between distinct eigenvalues). Quadratic convergence from the start is not given:
for a 6 x 6 matrix, ``off(A) / |A|`` typically falls below ``1e-16`` after 5-6 sweeps
(float64) and below ``1e-7`` after 4 (float32); :data:`DEFAULT_SWEEPS` = 8 leaves a margin.
Repeated or zero eigenvalues (rank-deficient Gram matrices) do not slow it down: their
eigenvectors are only defined up to a rotation of the eigenspace, which does not change
``V diag(f(lambda)) V^T``. The tests measure the residual ``off`` on random, clustered and
rank-deficient matrices and compare with LAPACK ``eigh``. Accuracy after convergence is backward
stable: eigenvalues to ``O(eps |A|)`` like LAPACK.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["DEFAULT_SWEEPS", "jacobi_eigh", "jacobi_eigh_bl", "round_robin"]

#: Sweeps used by the estimator's ``solver="jacobi"``.
DEFAULT_SWEEPS = 8


def round_robin(n: int) -> list[list[tuple[int, int]]]:
    """Rounds of disjoint index pairs covering every pair ``p < q < n`` once (circle method).

    Args:
        n: matrix size.

    Returns:
        ``n' - 1`` rounds (``n'`` = n rounded up to even) of pairs ``(p, q)``, ``p < q``; pairs
        with the padding index ``n`` are left out.

    Example:
        >>> round_robin(4)
        [[(0, 3), (1, 2)], [(0, 2), (1, 3)], [(0, 1), (2, 3)]]
    """
    m = n + (n % 2)
    players = list(range(m))
    rounds = []
    for _ in range(m - 1):
        pairs = []
        for i in range(m // 2):
            a, b = players[i], players[m - 1 - i]
            if a < n and b < n:
                pairs.append((min(a, b), max(a, b)))
        rounds.append(sorted(pairs))
        players = [players[0], players[-1], *players[1:-1]]  # rotate all but the first
    return rounds


def _round_constants(n: int, pairs: list[tuple[int, int]], like: Tensor):
    """Per-index constants of one round (model constants of the graph).

    Index ``i`` of a pair ``(p, q)`` has partner ``j`` (``q`` for ``p`` and ``p`` for ``q``) and
    sign ``+1`` (p) or ``-1`` (q); an index in no pair is its own partner and stays put.
    """
    partner, sign, paired = list(range(n)), [1.0] * n, [False] * n
    for a, b in pairs:
        partner[a], partner[b], sign[b] = b, a, -1.0
        paired[a] = paired[b] = True
    pp = [i if sign[i] > 0 else partner[i] for i in range(n)]  # p of i's pair
    qq = [partner[i] if sign[i] > 0 else i for i in range(n)]  # q of i's pair
    idx = torch.tensor(
        [p * n + p for p in pp]
        + [q * n + q for q in qq]
        + [p * n + q for p, q in zip(pp, qq, strict=True)],
        dtype=torch.long,
        device=like.device,
    )
    part = torch.tensor(partner, dtype=torch.long, device=like.device)
    half_sign = like.new_tensor(sign).mul(0.5).reshape(n, 1, 1)
    unpaired = None if all(paired) else ~torch.tensor(paired, device=like.device).reshape(n, 1, 1)
    return idx, part, half_sign, unpaired


def jacobi_eigh_bl(a: Tensor, sweeps: int = DEFAULT_SWEEPS) -> tuple[Tensor, Tensor]:
    """Eigen-decomposition of symmetric matrices stored batch-last, by cyclic Jacobi.

    Each rotation of a round is written per index ``i`` of its pair ``(p, q)``: with
    ``theta_i = sign_i atan(2 a_pq / (a_pp - a_qq)) / 2`` (``sign`` +1 for p, -1 for q; the
    Schur angle ``|theta| <= pi/4`` of GVL Alg. 8.5.1, ``tan 2 theta = 2 a_pq / (a_qq - a_pp)``
    up to the sign), row ``i`` of ``J^T A`` is ``cos(theta_i) A_i + sin(theta_i) A_partner(i)``
    and columns likewise, so one round is a few gathers and elementwise ops on all pairs at
    once (no rotation matrix is formed).

    Args:
        a: ``(n, n, B)`` symmetric matrices (only the symmetric part is used).
        sweeps: number of full sweeps (fixed: no data-dependent stopping, so it exports).

    Returns:
        ``lam (n, B)`` eigenvalues (unsorted) and ``V (n, n, B)`` with orthonormal eigenvectors as
        columns, ``a = V diag(lam) V^T``.
    """
    n = a.shape[0]
    m = 0.5 * (a + a.transpose(0, 1))
    eye = torch.eye(n, dtype=a.dtype, device=a.device).unsqueeze(-1)
    v = eye.expand_as(m)
    rounds = [_round_constants(n, pairs, a) for pairs in round_robin(n) if pairs]
    zero = a.new_zeros(())
    for _ in range(sweeps):
        for idx, part, half_sign, unpaired in rounds:
            # rotation angle of every index from a_pp, a_qq, a_pq of its pair
            app, aqq, apq = m.reshape(n * n, 1, -1).index_select(0, idx).split(n)  # (n, 1, B)
            x = apq / ((app - aqq) * half_sign)  # +-tan(2 theta); +-inf when a_pp = a_qq
            off0 = apq == 0 if unpaired is None else (apq == 0) | unpaired
            theta = 0.5 * torch.atan(torch.where(off0, zero, x))  # 0/0 -> no rotation
            c, s = torch.cos(theta), torch.sin(theta)
            # A <- J^T A J (rows, then columns together with V <- V J)
            m = c * m + s * m.index_select(0, part)
            mv = torch.cat((m, v), 0)
            c, s = c.transpose(0, 1), s.transpose(0, 1)  # (1, n, B)
            mv = c * mv + s * mv.index_select(1, part)
            m, v = mv.split(n, 0)
    diag = torch.arange(n, device=a.device) * (n + 1)
    return m.reshape(n * n, -1).index_select(0, diag), v


def jacobi_eigh(a: Tensor, sweeps: int = DEFAULT_SWEEPS) -> tuple[Tensor, Tensor]:
    """Like ``torch.linalg.eigh`` for ``(*B, n, n)`` symmetric matrices, eigenvalues ascending.

    Sorting uses ``torch.sort`` (ONNX TopK); inside the estimator the unsorted
    :func:`jacobi_eigh_bl` is used, which needs no sort.

    Args:
        a: ``(*B, n, n)`` symmetric matrices.
        sweeps: number of Jacobi sweeps.

    Returns:
        ``lam (*B, n)`` ascending and ``V (*B, n, n)`` with eigenvectors as columns.

    Example:
        >>> a = torch.tensor([[2.0, 1.0], [1.0, 2.0]], dtype=torch.float64)
        >>> lam, v = jacobi_eigh(a)
        >>> lam
        tensor([1., 3.], dtype=torch.float64)
    """
    batch, n = a.shape[:-2], a.shape[-1]
    lam, v = jacobi_eigh_bl(a.reshape(-1, n, n).permute(1, 2, 0), sweeps)
    lam, v = lam.T, v.permute(2, 0, 1)
    lam, order = lam.sort(-1)
    v = v.gather(-1, order.unsqueeze(-2).expand_as(v))
    return lam.reshape(*batch, n), v.reshape(*batch, n, n)
