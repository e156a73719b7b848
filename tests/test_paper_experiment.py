"""The paper's statistical analysis (Del Prete et al. 2012, Sec. 3) reproduced on the iCub."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from robots import load_model


def _example():
    path = Path(__file__).resolve().parents[1] / "examples" / "paper_experiment.py"
    spec = importlib.util.spec_from_file_location("paper_experiment", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_two_pure_forces_rank_5_and_half_gaussian_error():
    ex = _example()
    K = 10.0
    res = ex.run(load_model("icub"), frames=12_000, K=K, seed=3)
    assert (res["rank"] == 5).all() and (res["unknowns"] == 6).all()
    # the minimum-norm solution misses exactly the unobservable pair of equal and opposite forces
    # along the line through the contact points: per-force error = |(f1 - f2) . u| / 2
    u = np.diff(res["positions"], axis=1)[:, 0]  # link frame: both contacts on one link
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    expected = np.abs(np.einsum("ni,ni->n", res["truth"][:, 0] - res["truth"][:, 1], u)) / 2
    np.testing.assert_allclose(res["error"], np.stack([expected, expected], 1), atol=1e-9)
    # force balance still holds: the estimate's sum equals the truth's sum
    np.testing.assert_allclose(res["force"].sum(1), res["truth"].sum(1), atol=1e-9)
    s = ex.summary(res["error"], K)
    # 24,000 samples: standard errors are ~0.003 on shares and ~0.001 K on sigma
    assert abs(s["sigma_over_K"] - np.sqrt(2) / 6) < 0.005  # paper: ~K/4
    assert 0.66 < s["below_K_4"] < 0.74  # paper: 68%
    assert 0.94 < s["below_K_2"] < 0.99  # paper: 95%
