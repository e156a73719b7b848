"""Causal derivatives (torchcontact.online.derivatives): exact on polynomials, streaming equals
batched, chunking with context, the stated delay measured on a sinusoid."""

from __future__ import annotations

import numpy as np
import pytest

from torchcontact.errors import InputError
from torchcontact.online.derivatives import CausalDerivatives, causal_derivatives


def _uneven(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.integers(8_000_000, 12_000_000, n)).astype(np.int64)


@pytest.mark.parametrize("order", [2, 3, 4])
def test_exact_on_polynomials_of_its_degree(order):
    t = _uneven(60)
    s = (t - t[0]) * 1e-9
    coef = np.array([0.3, -1.2, 0.7, 0.4, -0.2])[: order + 1]
    q = np.polynomial.polynomial.polyval(s, coef)[:, None] * np.array([1.0, -2.0])
    d1 = np.polynomial.polynomial.polyval(s, np.polynomial.polynomial.polyder(coef))
    d2 = np.polynomial.polynomial.polyval(s, np.polynomial.polynomial.polyder(coef, 2))
    qh, qd, qdd = causal_derivatives(t, q, window=9, order=order)
    assert np.isnan(qd[:order]).all() and np.isfinite(qd[order:]).all()
    assert np.allclose(qh[order:], q[order:], atol=1e-9)
    assert np.allclose(qd[order:, 0], d1[order:], atol=1e-7)
    assert np.allclose(qdd[order:, 1], -2 * d2[order:], atol=1e-5)


def test_streaming_equals_batched_and_chunks_need_only_past_context():
    rng = np.random.default_rng(2)
    t = _uneven(80, 1)
    q = np.cumsum(rng.normal(size=(80, 3)), 0) * 0.01
    whole = causal_derivatives(t, q, window=11, order=3)
    f = CausalDerivatives(3, window=11, order=3)
    live = [f.update(ti, qi) for ti, qi in zip(t, q, strict=True)]
    for j in range(3):
        assert np.allclose(np.array([x[j] for x in live]), whole[j], equal_nan=True, atol=1e-12)
    # a chunk [40, 60) with window - 1 frames of context before it and none after
    part = causal_derivatives(t[30:60], q[30:60], window=11, order=3, lo=10, hi=30)
    for j in range(3):
        assert np.allclose(part[j], whole[j][40:60], atol=1e-12)


def test_stated_delay_is_the_measured_one():
    """order 2: qdd lags (window - 1) / 2 frames at low frequency; order 3: no lag."""
    period, f0 = 0.01, 0.2
    t = (np.arange(600) * period * 1e9).astype(np.int64)
    s = t * 1e-9
    w = 2 * np.pi * f0
    q = np.sin(w * s)[:, None]
    for order, window in ((2, 11), (3, 15)):
        delays = CausalDerivatives(1, window, order).delay(period, f0)
        _, qd, qdd = causal_derivatives(t, q, window, order)
        k = slice(100, None)
        basis = np.stack([np.cos(w * s[k]), np.sin(w * s[k])], -1)

        def phase(x, basis=basis):  # x ~ a cos + b sin = r sin(w s + phase)
            a, b = np.linalg.lstsq(basis, x, rcond=None)[0]
            return np.arctan2(a, b)

        for est, exact, d in ((qd[k, 0], w * np.cos(w * s[k]), delays[1]),
                              (qdd[k, 0], -(w**2) * np.sin(w * s[k]), delays[2])):  # fmt: skip
            lag = np.angle(np.exp(1j * (phase(exact) - phase(est)))) / w  # measured delay, s
            assert lag == pytest.approx(d, abs=1e-6)
    low = CausalDerivatives(1, 11, 2).delay(period)
    assert low[1] == pytest.approx(0.0, abs=1e-6) and low[2] == pytest.approx(5 * period, rel=1e-6)
    assert abs(CausalDerivatives(1, 15, 3).delay(period)[2]) < 1e-6


def test_bad_input():
    with pytest.raises(InputError, match="order"):
        CausalDerivatives(2, window=5, order=1)
    with pytest.raises(InputError, match="window"):
        causal_derivatives(np.arange(5), np.zeros((5, 1)), window=3, order=3)
    f = CausalDerivatives(2, 5, 2)
    f.update(10, [0.0, 0.0])
    with pytest.raises(InputError, match="not after"):
        f.update(10, [0.0, 0.0])
    with pytest.raises(InputError, match="2 values"):
        f.update(20, [0.0])
    with pytest.raises(InputError, match="increase"):
        causal_derivatives(np.array([0, 2, 1]), np.zeros((3, 1)))
