"""``estimate --constraints`` on logs: the cone fields in, ``converged``/``iterations``/
``cone_active``/``nullity`` out, the warm start across chunks, bad cone fields as per-frame
status, option errors."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.cli import main
from torchcontact.logs import LogConstraints, estimate_file, write_simulated_log

MU = 0.5
#: agreement of two runs whose frames start from other iterates (warm vs cold, other chunks),
#: N: the solver stops at relative KKT residuals of 1e-6, and the weak regularisation leaves the
#: optimum flat along the unobservable direction (measured: 2e-4 N on 19 N forces)
SOLVER_ATOL = 1e-3


@pytest.fixture(scope="module")
def cone_log(model, tmp_path_factory):
    """The demo's log: one or two pushing forces on the arm's skin, skin normals recorded."""
    path = tmp_path_factory.mktemp("cones") / "log.parquet"
    return write_simulated_log(model, 2000, path, seed=0)


def _forces(path):
    rows = pq.read_table(path).column("contacts").to_pylist()
    return np.array([c["force"] for row in rows for c in row], float)


def test_cli_keeps_pushing_forces_inside_their_cones(cone_log, tmp_path, capsys):
    out = tmp_path / "e.parquet"
    args = ["estimate", str(cone_log), "--out", str(out), "--quiet", "--batch-size", "512"]
    assert main([*args, "--constraints", "--friction", str(MU)]) == 0
    assert "cones: 100.00% of" in capsys.readouterr().out
    est, inp = pq.read_table(out), pq.read_table(cone_log)
    assert (est["status_code"].to_numpy() == 0).all()
    assert est["converged.base_ft"].to_numpy(zero_copy_only=False).all()
    its = est["iterations.base_ft"].to_numpy(zero_copy_only=False)
    assert its.max() <= 25 and its.max() > 0
    nullity = est["nullity.base_ft"].to_numpy()
    assert (nullity == est["unknowns.base_ft"].to_numpy() - est["rank.base_ft"].to_numpy()).all()
    assert (nullity == 1).any()  # two forces: the pseudo-inverse alone cannot tell them apart
    active = 0
    for row_in, row_out in zip(inp["contacts"].to_pylist(), est["contacts"].to_pylist(),
                               strict=True):  # fmt: skip
        for c_in, c_out in zip(row_in, row_out, strict=True):
            n = np.array(c_in["normal"]) / np.linalg.norm(c_in["normal"])  # outward
            f = np.array(c_out["force"])
            push = -(f @ n)
            assert push >= -1e-6 and np.linalg.norm(f + push * n) <= MU * push + 1e-6
            active += bool(c_out["cone_active"])
    assert active > 0
    # same answers warm-started in other chunks, and started cold, to the solver's accuracy
    cold = estimate_file(cone_log, model_path(), tmp_path / "c.parquet",
                         constraints=LogConstraints(friction=MU, warm_start=False))  # fmt: skip
    one = estimate_file(cone_log, model_path(), tmp_path / "o.parquet", batch_size=4096,
                        constraints=LogConstraints(friction=MU))  # fmt: skip
    for other in (cold, one):
        np.testing.assert_allclose(_forces(other["output"]), _forces(out), atol=SOLVER_ATOL)


def model_path():
    from torchcontact.robots import tcarm_path

    return tcarm_path()


def test_bad_cone_fields_get_a_status_and_the_rest_is_processed(cone_log, tmp_path):
    tab = pq.read_table(cone_log)
    rows = tab["contacts"].to_pylist()
    first = [i for i, r in enumerate(rows) if r]
    zero, negative, none = first[0], first[1], first[2]
    rows[zero][0]["normal"] = [0.0, 0.0, 0.0]
    rows[negative][0]["friction"] = -1.0
    rows[none][0]["normal"] = None
    bad = tab.set_column(
        tab.schema.get_field_index("contacts"), tab.schema.field("contacts"),
        pa.array(rows, tab.schema.field("contacts").type),
    )  # fmt: skip
    log = tmp_path / "bad.parquet"
    pq.write_table(bad, log)
    out = estimate_file(log, model_path(), tmp_path / "e.parquet",
                        constraints=LogConstraints(friction=MU))["output"]  # fmt: skip
    est = pq.read_table(out)
    code = est["status_code"].to_numpy()
    assert code[zero] & 8 and code[negative] & 4 and code[none] & 4
    detail = est["status_detail"].to_pylist()
    assert "zero-length contact normal" in detail[zero]
    assert "friction" in detail[negative] and "normal" in detail[none]
    rest = np.setdiff1d(np.arange(len(code)), [zero, negative, none])
    assert (code[rest] == 0).all()


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--friction", "0.5"], "apply with --constraints only"),
        (["--constraints", "--friction", "0.5", "--cone-angle", "0.5"], "not both"),
        (["--constraints", "--cone-angle", "2"], "(0, pi/2)"),
    ],
)
def test_bad_options_exit_2_before_writing(cone_log, tmp_path, capsys, extra, match):
    out = tmp_path / "e.parquet"
    assert main(["estimate", str(cone_log), "--out", str(out), "--quiet", *extra]) == 2
    assert match in capsys.readouterr().err
    assert not out.exists()
