import pyarrow.parquet as pq
import pytest

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def local_ray():
    # 2 CPUs: one for the estimating actor (actor_cpus=1, one actor), one for the read tasks
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_ray_engine_same_rows_as_local(model, sim_log, sim_log_q_only, tmp_path, local_ray):
    from torchcontact.logs import LogError, estimate_file
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    # small batches so that the log is several Ray blocks and batches
    r = estimate_file_ray(sim_log, tcarm_path(), tmp_path / "ray.parquet", batch_size=128)
    loc = estimate_file(sim_log, model, tmp_path / "local.parquet", batch_size=128)
    a, b = pq.read_table(r["output"]), pq.read_table(loc["output"])
    assert r["engine"] == "ray" and a.num_rows == b.num_rows == 600
    assert a.schema.metadata == b.schema.metadata
    # same rows; batches may differ in slot layout, so floats agree to rounding
    assert a["t_ns"].equals(b["t_ns"]) and a["status"].equals(b["status"])
    import numpy as np

    for col in ("joint_torques",):
        np.testing.assert_allclose(
            np.stack(a[col].to_numpy(zero_copy_only=False)),
            np.stack(b[col].to_numpy(zero_copy_only=False)),
            rtol=0,
            atol=1e-9,
        )
    fa = [c["force"] for row in a["contacts"].to_pylist() for c in row]
    fb = [c["force"] for row in b["contacts"].to_pylist() for c in row]
    np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
    with pytest.raises(LogError, match="needs qd and qdd"):
        estimate_file_ray(sim_log_q_only, tcarm_path(), tmp_path / "x.parquet")
