"""The bias tracker and smoother (torchcontact.online.bias) against closed forms and a batch
least-squares reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from torchcontact.errors import InputError
from torchcontact.online.bias import BiasTracker, process_noise, smooth_bias

STD = (0.05, 0.05, 0.05, 0.005, 0.005, 0.005)


def test_time_constant_is_the_stated_one():
    """In steady state an offset step decays as exp(-t / tau) at the nominal period."""
    tau, period = 0.5, 0.01
    tr = BiasTracker(["s"], time_constant=tau, period=period, ft_std=STD)
    for _ in range(2000):  # converge to the steady-state gain on a zero offset
        tr.update(np.zeros(6))
    step = np.array([2.0, -1.0, 0.5, 0.1, 0.0, 0.0])
    errs = [np.abs(tr.update(step).offset[0] - step).max() / 2.0 for _ in range(300)]
    for k in (49, 99, 199):  # t = 0.5, 1, 2 s
        assert errs[k] == pytest.approx(math.exp(-(k + 1) * period / tau), rel=1e-6)


def test_gating_and_since_update():
    tr = BiasTracker(["a", "b"], time_constant=0.1, period=0.01)
    z = np.array([[1.0] * 6, [2.0] * 6])
    s = tr.update(z, contact_free=[True, False], t=0.0)
    assert s.updated.tolist() == [True, False]
    assert s.offset[1].tolist() == [0.0] * 6 and s.since_update[1] == np.inf
    s = tr.update(z, contact_free=[False, False], t=0.25)
    assert s.since_update[0] == pytest.approx(0.25) and s.offset[0, 0] == pytest.approx(1.0, 1e-3)
    # uncertainty grows while not updated: p * R with p from the random walk
    assert s.cov[0, 0, 0] > tr.R[0, 0, 0] / 1e4
    nan = z.copy()
    nan[0, 2] = np.nan
    s2 = tr.update(nan, t=0.26)  # a non-finite residual never updates
    assert not s2.updated[0] and np.isfinite(s2.offset).all()
    with pytest.raises(InputError, match="decrease"):
        tr.update(z, t=0.1)
    with pytest.raises(InputError, match=r"\(2, 6\)"):
        tr.update(np.zeros(6))


def test_tare_refused_during_contact_and_averages():
    tr = BiasTracker(["s"], ft_std=STD)
    with pytest.raises(InputError, match="contact is active on sensor.*'s'"):
        tr.tare(np.ones((1, 6)), contact_free=False)
    z = np.array([[[1.0] * 6], [[3.0] * 6]])  # two frames
    s = tr.tare(z, [[True], [True]], frames=2)
    assert s.offset[0].tolist() == [2.0] * 6
    assert np.allclose(s.cov[0], tr.R[0] / 2)


def test_innovation_gate_rejects_a_spike_and_reacquires_a_step():
    tr = BiasTracker(["s"], time_constant=0.2, ft_std=STD, gate=22.46, gate_frames=5)
    for _ in range(200):
        tr.update(np.zeros(6))
    spike = np.array([5.0, 0, 0, 0, 0, 0])
    for _ in range(3):  # an unannounced 3-frame contact: rejected
        s = tr.update(spike)
        assert not s.updated[0]
    assert np.abs(tr.update(np.zeros(6)).offset).max() < 1e-9
    for _ in range(5):  # a real step: accepted after 5 rejected frames, then re-acquired fast
        s = tr.update(spike)
    assert s.updated[0] and s.offset[0, 0] == pytest.approx(5.0, abs=1e-3)


def test_bad_options():
    with pytest.raises(InputError, match="positive"):
        BiasTracker(["s"], time_constant=0.0)
    with pytest.raises(InputError, match="positive definite"):
        BiasTracker(["s"], ft_cov=np.zeros((6, 6)))
    with pytest.raises(InputError, match="not both"):
        BiasTracker(["s"], ft_std=STD, ft_cov=np.eye(6))
    with pytest.raises(InputError, match="positive"):
        process_noise(1.0, -0.01)


def _frames(seed=0, n=400):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.005, 0.015, n))  # uneven sampling
    free = rng.random((n, 2)) > 0.3
    free[100:180] = False  # a long contact on both sensors
    z = rng.normal(size=(n, 2, 6)) * np.array(STD) + np.linspace(0, 1, n)[:, None, None]
    return t, free, z


def test_forward_filter_is_the_online_tracker():
    t, free, z = _frames()
    tr = BiasTracker(["a", "b"], time_constant=0.3, period=0.01, ft_std=STD)
    states = [tr.update(z[k], free[k], t[k]) for k in range(len(t))]
    off = smooth_bias(z, free, t, time_constant=0.3, period=0.01, ft_std=STD, smoother=False)
    assert np.allclose(off.offset, [s.offset for s in states], rtol=0, atol=1e-12)
    cov = off.scale[..., None, None] * off.R
    assert np.allclose(cov, [s.cov for s in states], rtol=1e-12, atol=0)
    assert np.allclose(off.since_update, [s.since_update for s in states])
    assert off.updated.tolist() == free.tolist()


def test_smoother_is_the_batch_posterior():
    """RTS equals the posterior mean of the whole linear-Gaussian model, solved as one system."""
    t, free, z = _frames(1, 150)
    tau, period, prior = 0.3, 0.01, 1e4
    res = smooth_bias(z, free, t, time_constant=tau, period=period, ft_std=STD, prior_scale=prior)
    # in units of R each axis is independent: minimise
    #   x_0^2 / prior + sum_k (x_k - x_{k-1})^2 / q_k + sum_{free k} (z_k - x_k)^2
    q = process_noise(tau, period) / period * np.diff(t, prepend=t[0])
    n = len(t)
    for s in range(2):
        H = np.zeros((n, n))
        H[0, 0] += 1 / (prior + q[0]) if q[0] > 0 else 1 / prior
        for k in range(1, n):
            w = 1 / q[k]
            H[k, k] += w
            H[k - 1, k - 1] += w
            H[k, k - 1] -= w
            H[k - 1, k] -= w
        f = free[:, s]
        H[np.arange(n), np.arange(n)] += f
        x = np.linalg.solve(H, f[:, None] * z[:, s])
        assert np.allclose(res.offset[:, s], x, rtol=0, atol=1e-9)
        assert np.allclose(res.scale[:, s], np.diag(np.linalg.inv(H)), rtol=1e-8)


def test_smoother_bad_input():
    with pytest.raises(InputError, match=r"\(N, S, 6\)"):
        smooth_bias(np.zeros((5, 5)), np.ones(5, bool))
    with pytest.raises(InputError, match="contact_free"):
        smooth_bias(np.zeros((5, 6)), np.ones(4, bool))
    with pytest.raises(InputError, match="decrease"):
        smooth_bias(np.zeros((3, 6)), np.ones(3, bool), [0.0, 0.2, 0.1])


def _sequential(z, free, q, x0, p0):
    """The filter and RTS smoother frame by frame (the textbook recursions, one sensor)."""
    n = len(z)
    xf, pf, pp = np.zeros((n, 6)), np.zeros(n), np.zeros(n)
    x, p = x0.copy(), p0
    for k in range(n):
        p = p + q[k]
        pp[k] = p
        g = p / (p + 1.0) if free[k] else 0.0
        x = x + g * (z[k] - x) if free[k] else x
        p = p * (1.0 - g)
        xf[k], pf[k] = x, p
    xs, ps = xf.copy(), pf.copy()
    for k in range(n - 2, -1, -1):
        c = pf[k] / pp[k + 1]
        xs[k] = xf[k] + c * (xs[k + 1] - xf[k])
        ps[k] = pf[k] + c * c * (ps[k + 1] - pp[k + 1])
    return xf, pf, xs, ps


def test_bias_smoother_scans_equal_the_sequential_recursions():
    """``BiasSmoother``'s offsets by affine scans (forward in 3 chunks, backward in blocks of 50)
    equal the frame-by-frame filter and smoother, a gated stretch and uneven steps included."""
    from torchcontact.online.bias import BiasSmoother

    rng = np.random.default_rng(4)
    n = 400
    z = rng.normal(size=(n, 1, 6)) + np.linspace(0.0, 2.0, n)[:, None, None]
    free = rng.random(n) > 0.3
    free[150:260] = False
    t = np.cumsum(rng.uniform(0.005, 0.02, n))
    sm = BiasSmoother(1, time_constant=0.3, period=0.01, offset=np.ones((1, 6)))
    for a, b in ((0, 97), (97, 300), (300, n)):
        sm.forward(z[a:b], free[a:b], t[a:b])
    xf_scan = sm._parts and np.concatenate(sm._parts)[:, :6]
    sm.smooth(block=50)
    off, scale = sm.offsets(0, n)
    q = sm.q_rate * np.diff(t, prepend=t[0])
    xf, pf, xs, ps = _sequential(z[:, 0], free, q, np.ones(6), 1e4)
    np.testing.assert_allclose(xf_scan, xf, rtol=0, atol=1e-12 * np.abs(xf).max())
    np.testing.assert_allclose(off[:, 0], xs, rtol=0, atol=1e-12 * np.abs(xs).max())
    np.testing.assert_allclose(scale[:, 0], ps, rtol=1e-12)
