"""The minimum-norm solve (torchcontact.solve) against numpy's pinv and LAPACK eigh.

numpy.linalg.pinv (SVD) is the reference: ``x = A^T y`` with the pivoted-Cholesky ``y`` must equal
``pinv(A) b`` to 1e-9 (relative to the solution's scale) for full-rank and rank-deficient A,
including the estimator's own matrices: two pure forces (rank 5 of 6) and torque-sensor rows.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcontact.solve import RANK_RTOL, min_norm_solve, min_norm_solve_eigh


def _random_A(rng, rows, cols, rank, scale_rows=True):
    A = rng.normal(size=(rows, rank)) @ rng.normal(size=(rank, cols))
    if scale_rows:  # force rows in N, moment rows in N m with 0.05-0.5 m arms: mixed scales
        A *= rng.uniform(0.05, 2.0, size=(rows, 1))
    return A


@pytest.mark.parametrize("rank", [4, 5, 6])
@pytest.mark.parametrize("rows", [6, 9])  # 6 sensor rows, plus 3 torque rows
def test_matches_numpy_pinv(rank, rows):
    rng = np.random.default_rng(rank * 10 + rows)
    n, cols = 64, 9
    A = np.stack([_random_A(rng, rows, cols, rank) for _ in range(n)])
    b = rng.normal(size=(n, rows)) * 10
    s = min_norm_solve(torch.tensor(A @ A.transpose(0, 2, 1)), torch.tensor(b))
    x = np.einsum("nij,ni->nj", A, s.y.numpy())
    x_ref = np.stack([np.linalg.pinv(A[i], rcond=1e-10) @ b[i] for i in range(n)])
    assert (s.rank.numpy() == rank).all()
    np.testing.assert_allclose(x, x_ref, atol=1e-9 * np.abs(x_ref).max(), rtol=0)
    res_ref = np.linalg.norm(np.einsum("nij,nj->ni", A, x_ref) - b, axis=-1)
    np.testing.assert_allclose(s.residual.numpy(), res_ref, atol=1e-9 * np.abs(b).max(), rtol=0)
    assert not np.allclose(x[0], x[1])  # frames differ


def _two_forces(rng, n):
    """The paper's case: two pure forces seen by one F/T sensor, A = [[I, I], [C1, C2]]."""
    out = []
    for _ in range(n):
        c1, c2 = rng.normal(size=3) * 0.1, rng.normal(size=3) * 0.1
        skew = [np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]]) for c in (c1, c2)]
        out.append(np.block([[np.eye(3), np.eye(3)], [skew[0], skew[1]]]))
    return np.stack(out)


def test_two_pure_forces_rank_5_and_torque_rows_restore_rank_6():
    rng = np.random.default_rng(0)
    n = 100
    A = _two_forces(rng, n)
    f = rng.normal(size=(n, 6)) * 10
    b = np.einsum("nij,nj->ni", A, f)
    s = min_norm_solve(torch.tensor(A @ A.transpose(0, 2, 1)), torch.tensor(b))
    assert (s.rank.numpy() == 5).all()
    x = np.einsum("nij,ni->nj", A, s.y.numpy())
    x_ref = np.stack([np.linalg.pinv(A[i]) @ b[i] for i in range(n)])
    np.testing.assert_allclose(x, x_ref, atol=1e-9 * np.abs(x_ref).max(), rtol=0)
    # the minimum-norm solution splits the unobservable component (along c2 - c1) evenly
    assert np.abs(x - f).max() > 1e-3
    # one torque row per force along an axis through the other contact restores the rank
    rows = rng.normal(size=(n, 2, 6))
    Ab = np.concatenate([A, rows], axis=1)
    bb = np.einsum("nij,nj->ni", Ab, f)
    s2 = min_norm_solve(torch.tensor(Ab @ Ab.transpose(0, 2, 1)), torch.tensor(bb))
    assert (s2.rank.numpy() == 6).all()
    x2 = np.einsum("nij,ni->nj", Ab, s2.y.numpy())
    np.testing.assert_allclose(x2, f, atol=1e-9 * np.abs(f).max(), rtol=0)


def test_agrees_with_the_eigh_reference_and_handles_zero_and_tiny():
    rng = np.random.default_rng(1)
    A = np.stack([_random_A(rng, 6, 7, r) for r in (1, 2, 3, 6, 6, 5)])
    b = rng.normal(size=(6, 6))
    G, bt = torch.tensor(A @ A.transpose(0, 2, 1)), torch.tensor(b)
    a, e = min_norm_solve(G, bt), min_norm_solve_eigh(G, bt)
    assert torch.equal(a.rank, e.rank)
    xa = np.einsum("nij,ni->nj", A, a.y.numpy())
    xe = np.einsum("nij,ni->nj", A, e.y.numpy())
    np.testing.assert_allclose(xa, xe, atol=1e-9 * np.abs(xe).max(), rtol=0)
    zero = min_norm_solve(torch.zeros(2, 6, 6, dtype=torch.float64), bt[:2])
    assert (zero.rank == 0).all() and (zero.y == 0).all()
    torch.testing.assert_close(zero.residual, bt[:2].norm(dim=-1))


def test_rank_tolerance_is_relative_to_the_largest_diagonal():
    """A direction with singular value ratio s is kept iff s^2 > rtol (Gram squares it)."""
    for ratio, expected in ((1e-4, 6), (1e-6, 5)):
        d = np.ones(6)
        d[-1] = ratio
        A = np.diag(d)
        s = min_norm_solve(torch.tensor(A @ A.T)[None], torch.ones(1, 6, dtype=torch.float64))
        assert int(s.rank) == expected, (ratio, RANK_RTOL[torch.float64])


def test_float32_uses_its_own_tolerance():
    rng = np.random.default_rng(2)
    A = np.stack([_random_A(rng, 6, 6, 5) for _ in range(32)])
    b = rng.normal(size=(32, 6))
    G = torch.tensor(A @ A.transpose(0, 2, 1), dtype=torch.float32)
    s = min_norm_solve(G, torch.tensor(b, dtype=torch.float32))
    assert (s.rank == 5).all()
    x = np.einsum("nij,ni->nj", A, s.y.double().numpy())
    x_ref = np.stack([np.linalg.pinv(A[i], rcond=1e-5) @ b[i] for i in range(32)])
    assert np.abs(x - x_ref).max() <= 1e-3 * np.abs(x_ref).max()


def test_exports_to_onnx_and_runs_in_float64(tmp_path):
    """No LAPACK and no op onnxruntime lacks for double: the float64 graph loads and runs."""
    ort = pytest.importorskip("onnxruntime")

    class Solve(torch.nn.Module):
        def forward(self, G, b):
            s = min_norm_solve(G, b)
            return s.y, s.rank, s.residual

    rng = np.random.default_rng(3)
    A = np.stack([_random_A(rng, 6, 6, r) for r in (4, 5, 6, 6)])
    G, b = torch.tensor(A @ A.transpose(0, 2, 1)), torch.tensor(rng.normal(size=(4, 6)))
    path = tmp_path / "solve.onnx"
    torch.onnx.export(Solve(), (G, b), str(path), input_names=["G", "b"], dynamo=False,
                      output_names=["y", "rank", "residual"], opset_version=18)  # fmt: skip
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    y, rank, res = sess.run(None, {"G": G.numpy(), "b": b.numpy()})
    ref = min_norm_solve(G, b)
    np.testing.assert_allclose(y, ref.y.numpy(), atol=1e-12, rtol=0)
    np.testing.assert_array_equal(rank, ref.rank.numpy())


@pytest.mark.parametrize("rank", [4, 6])
def test_weighted_solve_is_whitened_numpy_lstsq(rank):
    """``weighted_solve_program``: ``A^T y = pinv(L^-1 A) L^-1 b`` (weighted least squares,
    minimum norm among its solutions), the residual unweighted ``|A x - b|``."""
    from torchcontact.solve import cholesky, weighted_solve_program

    rng = np.random.default_rng(rank)
    n, rows, cols = 32, 8, 9
    A = np.stack([_random_A(rng, rows, cols, rank) for _ in range(n)])
    b = rng.normal(size=(n, rows)) * 10
    M = rng.normal(size=(n, rows, rows)) * 0.3
    S = M @ M.transpose(0, 2, 1) + np.diag(rng.uniform(0.01, 1.0, rows))
    t = torch.tensor
    G = [[t(A @ A.transpose(0, 2, 1))[:, i, j] for j in range(rows)] for i in range(rows)]
    L = cholesky([[t(S)[:, i, j] for j in range(rows)] for i in range(rows)])
    y, rk, res, _ = weighted_solve_program(G, [t(b)[:, i] for i in range(rows)], L, 1e-10)
    x = np.einsum("nij,ni->nj", A, torch.stack(y, -1).numpy())
    for i in range(n):
        Lc = np.linalg.cholesky(S[i])
        Aw, bw = np.linalg.solve(Lc, A[i]), np.linalg.solve(Lc, b[i])
        x_ref = np.linalg.lstsq(Aw, bw, rcond=1e-10)[0]
        np.testing.assert_allclose(x[i], x_ref, atol=1e-9 * np.abs(x_ref).max(), rtol=0)
        r_ref = np.linalg.norm(A[i] @ x_ref - b[i])
        np.testing.assert_allclose(float(res[i]), r_ref, atol=1e-9 * np.abs(b).max(), rtol=0)
        # the weighted solution beats the unweighted one in the Mahalanobis norm
        x_pinv = np.linalg.pinv(A[i], rcond=1e-10) @ b[i]
        d = np.linalg.solve(Lc, A[i] @ x_pinv - b[i])
        assert np.linalg.norm(np.linalg.solve(Lc, A[i] @ x_ref - b[i])) <= np.linalg.norm(d) + 1e-9
    assert (rk.round().numpy() == rank).all()
