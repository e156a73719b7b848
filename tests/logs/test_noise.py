"""``estimate``'s noise-weighted solve on logs: where the noise comes from (``--ft-noise``, the
``ft_cov.<sensor>`` column, the profile in the log's metadata, the contact-free frames), that the
weighting helps, ``--unweighted``, and bad noise input as one ``error:`` line."""

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.cli import main
from torchcontact.logs import estimate_file, write_simulated_log
from torchcontact.logs.format import META_FT_NOISE, META_FT_PROFILES, ft_cov_column
from torchcontact.simulation import UnmodeledEffects

#: FT 300 datasheet noise, N and N m (the profile robotiq-ft300)
STD = np.array([0.1, 0.1, 0.1, 0.005, 0.005, 0.005])


@pytest.fixture(scope="module")
def noisy_log(model, tmp_path_factory):
    """600 frames of the tcarm with the FT 300's noise on the readings."""
    path = tmp_path_factory.mktemp("noise") / "log.parquet"
    fx = UnmodeledEffects(noise_std=tuple(STD))
    return write_simulated_log(model, 600, path, seed=3, effects=fx)


def _one_contact_errors(out):
    tab = pq.read_table(out)
    ok = tab["rank.base_ft"].to_numpy() == tab["unknowns.base_ft"].to_numpy()
    rows = tab["contacts"].to_pylist()
    return np.array([
        np.linalg.norm(np.subtract(r[0]["force"], r[0]["true_force"]))
        for r, good in zip(rows, ok, strict=True) if good and len(r) == 1
    ])  # fmt: skip


def _forces(out):
    rows = pq.read_table(out)["contacts"].to_pylist()
    return np.array([c["force"] for r in rows for c in r])


def _with(log, path, columns=None, meta=None):
    tab = pq.read_table(log)
    for name, col in (columns or {}).items():
        tab = tab.append_column(name, col)
    tab = tab.replace_schema_metadata({**tab.schema.metadata, **(meta or {})})
    pq.write_table(tab, path)
    return path


def test_noise_sources_in_order_and_the_weighting_helps(model, noisy_log, tmp_path, capsys):
    # nothing given: estimated from the contact-free frames, within 15 % of the truth
    s = estimate_file(noisy_log, model, tmp_path / "cf.parquet")
    n = s["noise"]["sensors"]["base_ft"]
    assert s["noise"]["weighted"] and n["source"].startswith("contact-free frames (")
    assert np.allclose(n["std"], STD, rtol=0.15)
    meta = json.loads(pq.read_schema(tmp_path / "cf.parquet").metadata[META_FT_NOISE])
    assert meta == s["noise"]
    u = estimate_file(noisy_log, model, tmp_path / "u.parquet", unweighted=True)
    assert u["noise"] == {"weighted": False, "reason": "--unweighted", "sensors": {}}
    e_w, e_u = _one_contact_errors(tmp_path / "cf.parquet"), _one_contact_errors(u["output"])
    assert len(e_w) > 200
    assert np.median(e_w) < 0.8 * np.median(e_u)  # measured: 0.073 against 0.101 N

    # a per-frame ft_cov column (the datasheet's covariance) ...
    cov = np.tile(np.diag(STD**2).reshape(1, 36), (600, 1))
    rows = [list(r) for r in cov]
    rows[5], rows[6] = None, [np.nan] * 36  # malformed values: that frame's status, not the run
    col = pa.array(rows, pa.list_(pa.float64(), 36))
    log_c = _with(noisy_log, tmp_path / "c.parquet", {ft_cov_column("base_ft"): col})
    c = estimate_file(log_c, model, tmp_path / "ec.parquet")
    assert c["noise"]["sensors"]["base_ft"] == {"source": "column ft_cov.base_ft", "std": None}
    est_c = pq.read_table(c["output"])
    assert np.flatnonzero(est_c["status_code"].to_numpy()).tolist() == [5, 6]
    assert est_c["status_detail"].to_pylist()[5:7] == [
        "ft_cov.base_ft is not 36 floats", "ft_cov.base_ft is not finite"
    ]  # fmt: skip
    # ... equals the same noise given on the command line, which comes first
    g = estimate_file(log_c, model, tmp_path / "eg.parquet", ft_noise=["base_ft=0.1,0.005"])
    assert g["noise"]["sensors"]["base_ft"]["source"] == "--ft-noise"
    fc, fg = _forces(c["output"]), _forces(g["output"])
    ok = np.isfinite(fc).all(1)
    assert (~ok).sum() == sum(len(r) for r in est_c["contacts"].to_pylist()[5:7])
    np.testing.assert_allclose(fc[ok], fg[ok], atol=1e-9)
    assert not np.allclose(_forces(g["output"]), _forces(u["output"]), atol=1e-3)

    # the profile named in the log's metadata: its datasheet noise, the same estimate again
    log_p = _with(noisy_log, tmp_path / "p.parquet",
                  meta={META_FT_PROFILES: json.dumps({"base_ft": "robotiq-ft300"})})  # fmt: skip
    p = estimate_file(log_p, model, tmp_path / "ep.parquet")
    assert p["noise"]["sensors"]["base_ft"] == {
        "source": "profile robotiq-ft300 (log metadata)",
        "std": STD.tolist(),
    }
    np.testing.assert_allclose(_forces(p["output"]), _forces(g["output"]), atol=1e-9)

    # measured joint torques (no noise known for their rows): unweighted, saying why
    tau = pa.array([[np.nan] * model.nv] * 600, pa.list_(pa.float64(), model.nv))
    log_t = _with(noisy_log, tmp_path / "t.parquet", {"tau_measured": tau})
    t = estimate_file(log_t, model, tmp_path / "et.parquet")["noise"]
    assert not t["weighted"] and "tau_measured" in t["reason"]

    # a covariance that is not symmetric positive definite, an unknown sensor: one error line
    bad = cov.copy()
    bad[7, 0] = -1.0  # row 7: fx variance < 0
    log_b = _with(noisy_log, tmp_path / "b.parquet", {ft_cov_column("base_ft"):
                  pa.FixedSizeListArray.from_arrays(pa.array(bad.reshape(-1)), 36)})  # fmt: skip
    for args, says in (
        ([str(log_b)], "ft_cov.base_ft of row 7 is not positive definite"),
        ([str(noisy_log), "--ft-noise", "wrist_ft=0.1,0.005"], "has no F/T sensor 'wrist_ft'"),
        ([str(noisy_log), "--ft-noise", "base_ft=0.1,-1"], "must be a finite number > 0"),
        ([str(noisy_log), "--ft-noise", "base_ft=0.1,0.2,0.3"], "give 2 (SIGMA_F,SIGMA_M) or 6"),
        ([str(noisy_log), "--ft-noise", "base_ft=0.1,0.005", "--unweighted"], "not both"),
    ):
        out = tmp_path / "x.parquet"
        assert main(["estimate", *args, "--robot", "tcarm", "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and says in err[0], err
        assert not out.exists()


def test_driver_logs_name_their_profile_and_the_profile_gives_the_datasheet_noise(tmp_path):
    from torchcontact.drivers.log import FTLogWriter
    from torchcontact.drivers.profiles import load_profile

    with FTLogWriter(tmp_path / "ft.parquet", "ft300", profile="robotiq-ft300") as log:
        log.append(1, np.zeros(6))
    meta = pq.read_schema(tmp_path / "ft.parquet").metadata
    assert json.loads(meta[META_FT_PROFILES]) == {"ft300": "robotiq-ft300"}
    assert load_profile("robotiq-ft300").noise_std == tuple(STD)
    assert load_profile("generic-float32").noise_std is None  # no datasheet: no noise


def test_the_run_reuses_the_tables_the_noise_estimate_read(model, noisy_log, tmp_path, monkeypatch):
    """The first chunks read and decoded for the contact-free noise are not read again, and the
    decoding goes on where the noise stopped when it kept every chunk: same output bytes."""
    from torchcontact.logs import pipeline

    monkeypatch.setattr(pipeline, "NOISE_BATCH", 64)  # several noise chunks on a short log
    calls = []
    read = pipeline.read_chunks

    def counted(pf, columns, batch_size, source, first_row=0):
        calls.append(first_row)
        return read(pf, columns, batch_size, source, first_row)

    monkeypatch.setattr(pipeline, "read_chunks", counted)
    outs = {}
    for keep in (0, 3, 1000):
        monkeypatch.setattr(pipeline, "NOISE_KEEP", keep)
        calls.clear()
        s = estimate_file(noisy_log, model, tmp_path / f"k{keep}.parquet", batch_size=64)
        assert s["noise"]["sensors"]["base_ft"]["source"].startswith("contact-free frames (")
        outs[keep] = (pq.read_table(s["output"]), list(calls))
    assert outs[3][0].equals(outs[0][0]) and outs[1000][0].equals(outs[0][0])
    assert outs[0][1][-1] == 0 and outs[3][1][-1] == 3 * 64  # the run reads from the 4th chunk
    assert outs[1000][1] == [0]  # one read of the log, the noise's and the run's


def test_the_noise_estimates_forward_model_kernel_builds_after_the_run(
    model, noisy_log, tmp_path, monkeypatch
):
    # the noise estimate runs its forward model on the tape VM when the kernel is not built (no
    # build of its own during the run, while the estimator's may be pending); the kernel is left
    # to build once the process exits
    from torchcontact import kernels

    monkeypatch.setenv("TORCHCONTACT_VM", "1")
    monkeypatch.setattr(kernels, "AUTO_BUILD_MIN_FRAMES", 64)
    deferred = []
    monkeypatch.setattr(kernels, "_defer_build", lambda prog, dtype: deferred.append(prog.name))
    builds = []
    real = kernels.compiled

    def compiled(prog, dtype, device="cpu", wait=True, build=True):
        builds.append((prog.name, build))
        return None if prog.name == "predict" else real(prog, dtype, device, wait, build)

    monkeypatch.setattr(kernels, "compiled", compiled)
    s = estimate_file(noisy_log, model, tmp_path / "a.parquet")
    assert s["noise"]["weighted"]
    assert ("predict", True) not in builds  # looked up, never built during the run
    assert "predict" in deferred  # left for after the process


def test_a_resume_keeps_the_recorded_noise_when_only_rounding_differs():
    from torchcontact.logs.pipeline import recorded_noise
    from torchcontact.noise import FTNoise, SensorNoise

    class Run:
        def __init__(self, std):
            self.noise = FTNoise({"s": SensorNoise("contact-free frames (90 pairs)", std)})

        def set_noise(self, noise):
            self.noise = noise

    std = tuple(float(v) for v in STD)
    rounded = [v * (1 + 3e-16) + 1e-18 for v in std]
    for prev_std, adopted in ((rounded, True), ([v * 1.001 for v in std], False)):
        le = Run(std)
        prev = {"noise": {**le.noise.summary(), "sensors": {
            "s": {"source": "contact-free frames (90 pairs)", "std": prev_std}}}}  # fmt: skip
        recorded_noise(le, prev)
        assert list(le.noise.sensors["s"].std) == (prev_std if adopted else list(std))
    le = Run(std)  # another source: kept
    prev = {
        "noise": {**le.noise.summary(), "sensors": {"s": {"source": "--ft-noise", "std": rounded}}}
    }
    recorded_noise(le, prev)
    assert le.noise.sensors["s"].std == std
    recorded_noise(le, None)  # not a resume
    assert le.noise.sensors["s"].std == std


@pytest.mark.parametrize("n", [1, 2, 3, 50, 51, 2000])
def test_median_is_numpys(n):
    """The noise estimate's median (no numpy.ma import) gives numpy's numbers exactly."""
    from torchcontact.logs.noise import _median

    x = np.random.default_rng(n).standard_normal((n, 6)) * np.arange(1, 7)
    np.testing.assert_array_equal(_median(x), np.median(x, 0))
