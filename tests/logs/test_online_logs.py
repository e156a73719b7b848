"""``estimate --track-bias`` and ``--derivatives causal``: the online module's tracker, smoother
and causal differentiator run over logs (issue 23), on small simulated tcarm logs."""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from torchcontact.errors import InputError, LogError
from torchcontact.logs import estimate_file, write_simulated_log
from torchcontact.logs.chunks import LogBias, decoded_chunks
from torchcontact.logs.format import META_BIAS, META_DERIVED
from torchcontact.logs.pipeline import prepare, read_chunks
from torchcontact.online.bias import BiasSmoother, smooth_bias
from torchcontact.online.derivatives import CausalDerivatives
from torchcontact.simulation import UnmodeledEffects
from torchcontact.status import Status

NOISE = (0.05,) * 3 + (0.005,) * 3
# an offset and a thermal drift of ~3 N within the log (20 s at 100 Hz when 2000 frames)
DRIFT = UnmodeledEffects(
    offset=(1.0, -0.5, 0.8, 0.02, 0.01, -0.02),
    drift=(2.0, 1.0, -1.5, 0.05, 0.0, 0.03),
    drift_time_constant=5.0,
    noise_std=NOISE,
)


@pytest.fixture(scope="module")
def drift_log(model, tmp_path_factory):
    path = tmp_path_factory.mktemp("drift") / "log.parquet"
    return write_simulated_log(model, 900, path, seed=5, effects=DRIFT)


def _one_contact_rmse(path):
    tab = pq.read_table(path, columns=["contacts", "status_code"]).to_pylist()
    err = [np.subtract(r["contacts"][0]["force"], r["contacts"][0]["true_force"])
           for r in tab if r["status_code"] == 0 and len(r["contacts"]) == 1]  # fmt: skip
    return float(np.sqrt((np.square(err)).sum(1).mean())), len(err)


def test_bias_smoother_in_chunks_with_a_file_equals_smooth_bias(tmp_path):
    rng = np.random.default_rng(1)
    N = 700
    z = rng.normal(size=(N, 2, 6)) * 0.05 + np.linspace(0, 2, N)[:, None, None]
    free = rng.random((N, 2)) > 0.3
    z[5, 1] = np.nan  # not measured
    t = np.cumsum(rng.uniform(0.005, 0.015, N))
    ref = smooth_bias(z, free, t, time_constant=0.3, period=0.01, offset=np.ones((2, 6)))
    sm = BiasSmoother(2, time_constant=0.3, period=0.01, offset=np.ones((2, 6)),
                      store=tmp_path / "states")  # fmt: skip
    for a in range(0, N, 97):
        sm.forward(z[a : a + 97], free[a : a + 97], t[a : a + 97])
    sm.smooth(block=50)  # the backward pass over blocks of the file
    assert (tmp_path / "states").stat().st_size == N * 8 * (2 * 6 + 2 * 2)
    off, scale = sm.offsets(0, N)
    np.testing.assert_allclose(off, ref.offset, rtol=0, atol=1e-12)
    np.testing.assert_allclose(scale, ref.scale, rtol=1e-12)
    np.testing.assert_allclose(sm.std(scale), ref.std(), rtol=1e-12)
    sm.close()
    with pytest.raises(InputError, match="decrease"):
        BiasSmoother(1).forward(np.zeros((2, 6)), [True, True], [0.2, 0.1])


def test_track_bias_removes_a_drifting_offset(model, drift_log, tmp_path):
    # unweighted: the noise-weighted solve leans on the moment rows, which the force offset
    # does not touch, and so hides part of the drift this test is about
    plain = estimate_file(drift_log, model, tmp_path / "plain.parquet", unweighted=True)
    assert "bias" not in plain
    rmse_plain, n = _one_contact_rmse(tmp_path / "plain.parquet")
    out = tmp_path / "tracked.parquet"
    s = estimate_file(drift_log, model, out, batch_size=256, track_bias=True, unweighted=True)
    rmse, n2 = _one_contact_rmse(out)
    assert n == n2 > 100
    # measured: 1.6 N without tracking, 0.07 N tracked (the noise floor of a drift-free log)
    assert rmse_plain > 1.0 and rmse < 0.15
    b = s["bias"]["sensors"]["base_ft"]
    assert 200 < b["contact_free_frames"] < 900
    truth_last = np.add(DRIFT.offset, np.multiply(DRIFT.drift, 1 - np.exp(-8.99 / 5.0)))
    np.testing.assert_allclose(b["last"][:3], truth_last[:3], atol=0.05)
    tab = pq.read_table(out)
    assert json.loads(tab.schema.metadata[META_BIAS])["time_constant"] == 0.5
    bias = np.stack(tab.column("bias.base_ft").to_numpy(zero_copy_only=False))
    std = np.stack(tab.column("bias_std.base_ft").to_numpy(zero_copy_only=False))
    assert bias.shape == std.shape == (900, 6) and (std > 0).all()
    np.testing.assert_allclose(bias[-1], b["last"])
    assert not out.with_name("tracked.parquet.partial").exists()  # the states went with it
    # an interrupted run resumes (the bias pass reruns over the whole log): the same output
    from torchcontact.logs import chunks

    orig, calls = chunks.LogEstimator.estimate, []

    def crash(self, *a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("simulated crash")
        return orig(self, *a, **k)

    again = tmp_path / "again.parquet"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(chunks.LogEstimator, "estimate", crash)
        with pytest.raises(RuntimeError, match="simulated crash"):
            estimate_file(drift_log, model, again, batch_size=256, track_bias=True,
                          unweighted=True)  # fmt: skip
    with pytest.raises(LogError, match="other inputs or options"):  # not without --track-bias
        estimate_file(drift_log, model, again, batch_size=256, resume=True, unweighted=True)
    r = estimate_file(drift_log, model, again, batch_size=256, track_bias=True, resume=True,
                      unweighted=True)  # fmt: skip
    assert r["resumed_chunks"] == 2 and pq.read_table(again).equals(tab)
    # the causal filter alone: what the robot tracks online, worse inside contacts
    s2 = estimate_file(drift_log, model, tmp_path / "f.parquet", track_bias=LogBias(smoother=False),
                       unweighted=True)  # fmt: skip
    assert rmse < _one_contact_rmse(tmp_path / "f.parquet")[0] < rmse_plain
    assert s2["bias"]["method"] == "Kalman filter"


def test_causal_derivatives_match_the_online_filter(model, sim_log_q_only):
    """The pipeline's causal qd/qdd, over chunks of 64 frames, are the live loop's filter."""
    _, le, columns, _ = prepare(sim_log_q_only, model, causal=(15, 3))
    pf = pq.ParquetFile(sim_log_q_only)
    ds = list(decoded_chunks(le, read_chunks(pf, columns, 64, "log"), 5))
    qd, qdd = (np.concatenate([getattr(d, k) for d in ds]) for k in ("qd", "qdd"))
    q = np.concatenate([d.q for d in ds])
    t = np.concatenate([d.t for d in ds])
    live = CausalDerivatives(model.nv, 15, 3)
    ref = [live.update(ti, qi) for ti, qi in zip(t, q, strict=True)]
    np.testing.assert_allclose(qd, np.stack([r[1] for r in ref]), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(qdd, np.stack([r[2] for r in ref]), rtol=1e-9, atol=1e-7)
    assert np.isnan(qd[:3]).all() and np.isfinite(qd[3:]).all()
    short = np.concatenate([d.short for d in ds])
    assert short[:3].all() and not short[3:].any()


def test_estimate_causal_metadata_and_first_frames(model, sim_log_q_only, tmp_path):
    out = tmp_path / "c.parquet"
    s = estimate_file(sim_log_q_only, model, out, derivatives="causal")
    assert "causal" in s["derivatives"] and "delay" in s["derivatives"]
    tab = pq.read_table(out)
    assert "causal" in json.loads(tab.schema.metadata[META_DERIVED])["method"]
    code = tab.column("status_code").to_numpy()
    assert (code[:3] == int(Status.NOT_DIFFERENTIABLE)).all() and (code[3:] == 0).all()
    with pytest.raises(InputError, match="window"):
        estimate_file(sim_log_q_only, model, tmp_path / "x.parquet", derivatives="causal",
                      derivative_window=3)  # fmt: skip
    with pytest.raises(InputError, match="centred or causal"):
        estimate_file(sim_log_q_only, model, tmp_path / "x.parquet", derivatives="forward")


def test_cli_refusals_name_the_option(sim_log, tmp_path, capsys):
    from torchcontact.cli import main

    base = ["estimate", str(sim_log), "--robot", "tcarm", "--out", str(tmp_path / "o.parquet")]
    cases = [
        (["--track-bias", "--engine", "ray"], "--track-bias applies to --engine local only"),
        (["--derivatives", "causal", "--engine", "ray"], "--derivatives causal applies to"),
        (["--no-smoother"], "apply with --track-bias"),
        (["--track-bias", "--ft-std", "1,2"], "--ft-std: give 6 positive numbers"),
        (["--track-bias", "--bias-time-constant", "0"], "--bias-time-constant must be > 0"),
        (["--derivative-order", "2"], "apply with --derivatives causal"),
    ]
    for extra, message in cases:
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and err.count("\n") == 1
    assert not (tmp_path / "o.parquet").exists()
