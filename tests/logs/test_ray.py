"""``--engine ray`` on one small local Ray instance: the local engine's rows and summary, qd/qdd
derived across unit edges, resume, quiet output."""

import numpy as np
import pyarrow.parquet as pq
import pytest

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def local_ray():
    # 2 CPUs: the tasks (one CPU each) and the driver
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def small_groups(sim_log_q_only, tmp_path_factory):
    """The q-only simulated log in row groups of 100 frames (units cut through them)."""
    path = tmp_path_factory.mktemp("ray") / "q.parquet"
    pq.write_table(pq.read_table(sim_log_q_only), path, row_group_size=100)
    return path


def _same_rows(a, b):
    assert a["t_ns"].equals(b["t_ns"]) and a["status"].equals(b["status"])
    assert a.schema.metadata == b.schema.metadata
    for col in ("joint_torques",):
        np.testing.assert_allclose(
            np.stack(a[col].to_numpy(zero_copy_only=False)),
            np.stack(b[col].to_numpy(zero_copy_only=False)),
            rtol=0,
            atol=1e-9,
        )
    fa = [c["force"] for row in a["contacts"].to_pylist() for c in row]
    fb = [c["force"] for row in b["contacts"].to_pylist() for c in row]
    np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)  # slot layouts differ per chunk


def test_ray_engine_same_rows_and_summary_as_local(model, small_groups, tmp_path, local_ray, capfd):
    from torchcontact.logs import estimate_file
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    r = estimate_file_ray(
        small_groups, tcarm_path(), tmp_path / "ray.parquet", batch_size=64, task_rows=250
    )
    err = capfd.readouterr().err
    assert "INFO" not in err and "WARNING" not in err  # no Ray log lines, one progress bar
    loc = estimate_file(small_groups, model, tmp_path / "local.parquet", batch_size=64)
    assert set(r) == set(loc) and r["engine"] == "ray" and r["chunks"] == 3
    for k in ("frames", "processed_now", "ok_now", "bad_now", "sensors", "derived"):
        assert r[k] == loc[k], k
    assert r["derived"] == ["qd", "qdd"]  # derived across the edges of the units
    _same_rows(pq.read_table(r["output"]), pq.read_table(loc["output"]))


def test_ray_engine_resumes(model, small_groups, tmp_path, local_ray, monkeypatch):
    from torchcontact.logs import LogError, estimate_file
    from torchcontact.logs import format as pl
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    out = tmp_path / "r.parquet"

    def crash(self, *a, **k):  # killed after every unit, before the output is complete
        raise KeyboardInterrupt

    monkeypatch.setattr(pl.LogWriter, "close", crash)
    kw = dict(batch_size=64, task_rows=250)
    with pytest.raises(KeyboardInterrupt):
        estimate_file_ray(small_groups, tcarm_path(), out, **kw)
    monkeypatch.undo()
    partial = tmp_path / "r.parquet.partial"
    assert not out.exists() and not (tmp_path / "r.parquet.tmp").exists()
    (partial / "part-00000001.arrow").unlink()  # as if that unit had not finished
    with pytest.raises(LogError, match="pass --resume"):
        estimate_file_ray(small_groups, tcarm_path(), out, **kw)
    with pytest.raises(LogError, match="other inputs or options"):
        estimate_file_ray(small_groups, tcarm_path(), out, batch_size=32, resume=True)
    s = estimate_file_ray(small_groups, tcarm_path(), out, resume=True, **kw)
    assert s["resumed_chunks"] == 2 and s["processed_now"] == 250 and s["frames"] == 600
    assert not partial.exists() and not (tmp_path / "r.parquet.progress.json").exists()
    ref = estimate_file(small_groups, model, tmp_path / "ref.parquet", batch_size=64)
    _same_rows(pq.read_table(out), pq.read_table(ref["output"]))


def test_ray_engine_refuses_what_it_cannot_do(model, sim_log, tmp_path, capsys):
    import torch

    from torchcontact.cli import main
    from torchcontact.logs import LogError
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.residual import FeatureSpec, ResidualCorrection, ResidualGRU
    from torchcontact.robots import tcarm_path

    spec = FeatureSpec.default(model, "base_ft")
    torch.manual_seed(0)
    stack = ResidualCorrection(
        model, "base_ft", learned=ResidualGRU(len(spec.names(model)), 4), features=spec
    )
    gru = stack.save(tmp_path / "gru")
    with pytest.raises(LogError, match="cannot use a recurrent"):
        estimate_file_ray(sim_log, tcarm_path(), tmp_path / "o.parquet", residual=gru)
    out = str(tmp_path / "o.parquet")
    assert main(["estimate", str(sim_log), "--out", out, "--engine", "ray", "--workers", "0"]) == 2
    assert "--workers must be an integer >= 1" in capsys.readouterr().err
