"""The exportable Jacobi eigensolver against LAPACK eigh, alone and inside the estimator."""

from __future__ import annotations

import pytest
import torch
from export_scenes import scene

import torchcontact as tc
from torchcontact._jacobi import DEFAULT_SWEEPS, jacobi_eigh, round_robin


@pytest.mark.parametrize("n", [2, 5, 6, 9])
def test_round_robin_covers_every_pair_once(n):
    pairs = [p for r in round_robin(n) for p in r]
    assert sorted(pairs) == [(p, q) for p in range(n) for q in range(p + 1, n)]
    for r in round_robin(n):  # pairs of a round are disjoint
        idx = [i for p in r for i in p]
        assert len(idx) == len(set(idx))


@pytest.mark.parametrize("n", [6, 7])
@pytest.mark.parametrize("deficient", [0, 1, 2])
def test_jacobi_matches_eigh(n, deficient):
    g = torch.Generator().manual_seed(n + 10 * deficient)
    x = torch.randn(100, n, n - deficient, generator=g, dtype=torch.float64)
    x = x * torch.logspace(0, -3, n - deficient, dtype=torch.float64)  # spread eigenvalues
    a = x @ x.mT
    lam, v = jacobi_eigh(a)
    lam_ref = torch.linalg.eigh(a).eigenvalues
    scale = lam_ref[..., -1:]
    assert torch.allclose(lam / scale, lam_ref / scale, atol=1e-14, rtol=0)
    assert torch.allclose(v.mT @ v, torch.eye(n, dtype=a.dtype).expand_as(v), atol=1e-14)
    rec = v @ torch.diag_embed(lam) @ v.mT
    assert ((rec - a).abs().amax((-1, -2)) / scale.squeeze(-1)).max() < 1e-14


def test_sweep_count_margin():
    """Convergence bound documented in _jacobi: off(A)/|A| < 1e-14 after 6 of the 8 sweeps."""
    g = torch.Generator().manual_seed(3)
    x = torch.randn(300, 6, 6, generator=g, dtype=torch.float64)
    a = x @ x.mT
    lam, v = jacobi_eigh(a, sweeps=6)
    d = v.mT @ a @ v
    off = (d - torch.diag_embed(torch.diagonal(d, dim1=-2, dim2=-1))).norm(dim=(-1, -2))
    assert (off / a.norm(dim=(-1, -2))).max() < 1e-13
    assert DEFAULT_SWEEPS >= 8
    lam4, _ = jacobi_eigh(a, sweeps=4)  # and the count matters: 4 sweeps are not enough
    assert (lam4 - lam).abs().max() > 1e-12


@pytest.mark.parametrize("robot", ["tcarm", "icub"])
def test_estimator_jacobi_equals_eigh(robot):
    model, est, links, kinds, x, _ = scene(robot, 64, seed=1)
    ej = tc.ContactEstimator(model, est.sensor_names, solver="jacobi")
    ft = {s: x["ft"][:, i] for i, s in enumerate(est.sensor_names)}
    c = tc.Contacts(links, kinds, x["positions"], x["directions"], x["wrenches"], x["active"] > 0)
    ref = est.estimate(x["q"], x["qd"], x["qdd"], ft, c)
    got = ej.estimate(x["q"], x["qd"], x["qdd"], ft, c)
    rank = torch.stack([ref.rank[s] for s in est.sensor_names], -1)
    unk = torch.stack([ref.unknowns[s] for s in est.sensor_names], -1)
    assert (rank < unk).any() and (rank == unk).any()  # both kinds of frames are tested
    assert (rank == 5).any()  # two pure forces in one region
    for s in est.sensor_names:
        assert torch.equal(ref.rank[s], got.rank[s])
        assert torch.allclose(ref.residual[s], got.residual[s], atol=1e-9, rtol=0)
    ident = (rank == unk).all(-1)
    for a, b in ((ref.force, got.force), (ref.moment, got.moment)):
        assert torch.allclose(a[ident], b[ident], atol=1e-10, rtol=0)
        assert torch.allclose(a, b, atol=1e-9, rtol=0)  # minimum-norm solution too
    assert torch.allclose(ref.joint_torques, got.joint_torques, atol=1e-9, rtol=0)


def test_unknown_solver_is_refused():
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    with pytest.raises(ValueError, match="solver"):
        tc.ContactEstimator(model, solver="svd")
