"""Exportable symmetric eigensolver: batched parallel cyclic Jacobi with a fixed sweep count.

ONNX has no SVD, eigendecomposition, inverse or solve, so the contact estimator's small Gram
matrix ``G = A A^T`` (6 x 6, or 6 + m with torque rows) is diagonalised here with plain elementwise
torch ops and constant indexing only; ``torch.onnx.export`` turns it into a straight-line graph.

**Algorithm** (Golub & Van Loan, *Matrix Computations*, 4th ed., Sec. 8.5.2 cyclic Jacobi and
8.5.4-8.5.5 the parallel "round-robin" ordering). A sweep visits every pair ``(p, q)`` once; the
pairs are grouped into ``n' - 1`` rounds of ``n'/2`` disjoint pairs (``n'`` = n rounded up to
even; a padding index is a no-op), and the rotations of one round commute, so each round is one
orthogonal ``J`` and ``A <- J^T A J``, ``V <- V J``. Each rotation is the symmetric Schur
rotation that zeroes ``a_pq`` (GVL Alg. 8.5.1), computed in the overflow-safe form
``t = sign(tau) / (|tau| + sqrt(1 + tau^2))``.

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
    """Gather indices and scatter matrices of one round (model constants of the graph)."""
    p = torch.tensor([a for a, _ in pairs], dtype=torch.long, device=like.device)
    q = torch.tensor([b for _, b in pairs], dtype=torch.long, device=like.device)
    k = len(pairs)
    # J = I + Mc (c - 1) + Ms s with J_pp = J_qq = c, J_pq = s, J_qp = -s (flattened row-major)
    Mc = torch.zeros(n * n, k, dtype=like.dtype, device=like.device)
    Ms = torch.zeros(n * n, k, dtype=like.dtype, device=like.device)
    for i, (a, b) in enumerate(pairs):
        Mc[a * n + a, i] = Mc[b * n + b, i] = 1.0
        Ms[a * n + b, i] = 1.0
        Ms[b * n + a, i] = -1.0
    return p * n + p, q * n + q, p * n + q, Mc, Ms


def jacobi_eigh_bl(a: Tensor, sweeps: int = DEFAULT_SWEEPS) -> tuple[Tensor, Tensor]:
    """Eigen-decomposition of symmetric matrices stored batch-last, by cyclic Jacobi.

    Args:
        a: ``(n, n, B)`` symmetric matrices (only the symmetric part is used).
        sweeps: number of full sweeps (fixed: no data-dependent stopping, so it exports).

    Returns:
        ``lam (n, B)`` eigenvalues (unsorted) and ``V (n, n, B)`` with orthonormal eigenvectors as
        columns, ``a = V diag(lam) V^T``.
    """
    n = a.shape[0]
    a = 0.5 * (a + a.transpose(0, 1))
    flat = a.reshape(n * n, -1)  # (n*n, B)
    eye = torch.eye(n, dtype=a.dtype, device=a.device).reshape(n * n, 1)
    v = eye.expand_as(flat)
    rounds = [_round_constants(n, pairs, a) for pairs in round_robin(n) if pairs]
    one = a.new_ones(())
    for _ in range(sweeps):
        for ipp, iqq, ipq, Mc, Ms in rounds:
            app = flat.index_select(0, ipp)  # (k, B)
            aqq = flat.index_select(0, iqq)
            apq = flat.index_select(0, ipq)
            # symmetric Schur rotation zeroing a_pq (GVL Alg. 8.5.1)
            nz = apq != 0
            tau = (aqq - app) / (2 * torch.where(nz, apq, one))
            sgn = torch.where(tau >= 0, one, -one)
            t = sgn / (tau.abs() + torch.sqrt(1 + tau * tau))
            t = torch.where(nz, t, torch.zeros_like(t))
            c = torch.rsqrt(1 + t * t)
            s = t * c
            j = (eye + Mc @ (c - 1) + Ms @ s).reshape(n, n, -1)  # (n, n, B)
            m = flat.reshape(n, n, -1)
            # A <- J^T A J; V <- V J (broadcast multiply-sums over the small dims)
            jta = (j.unsqueeze(2) * m.unsqueeze(1)).sum(0)
            m = (jta.unsqueeze(2) * j.unsqueeze(0)).sum(1)
            vm = v.reshape(n, n, -1)
            vm = (vm.unsqueeze(2) * j.unsqueeze(0)).sum(1)
            flat, v = m.reshape(n * n, -1), vm.reshape(n * n, -1)
    diag = torch.arange(n, device=a.device) * (n + 1)
    return flat.index_select(0, diag), v.reshape(n, n, -1)


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
