import pyarrow.parquet as pq

from torchcontact.cli import main
from torchcontact.logs.plot import plot_log
from torchcontact.robots import tcarm_path


def test_demo_writes_log_estimate_and_pngs(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--frames", "400", "--out", str(out), "--noise", "0.01"]) == 0
    printed = capsys.readouterr().out
    pngs = ("forces.png", "quality.png", "robot.png", "nullspace.png")
    for name in ("log.parquet", "estimate.parquet", *pngs):
        assert (out / name).exists() and str(out / name) in printed
        assert (out / name).stat().st_size > 1000
    assert pq.read_table(out / "log.parquet").column_names[-1] == "temperature"
    # with the extra 'view' installed, a rerun recording of the same log and estimate
    try:
        import rerun  # noqa: F401
    except ImportError:
        assert "pip install 'torchcontact[view]'" in printed
    else:
        rrd = out / "demo.rrd"
        assert rrd.stat().st_size > 100_000 and f"rerun {rrd}" in printed


def test_plot_cli_frame_and_simulate_effects(tmp_path, capsys):
    log = tmp_path / "s.parquet"
    args = ["simulate", "--frames", "300", "--out", str(log), "--offset", "1", "--payload", "0.2"]
    assert main([*args, "--no-temperature", "--seed", "2"]) == 0
    assert "temperature" not in pq.read_schema(log).names
    est = tmp_path / "e.parquet"
    assert main(["estimate", str(log), "--out", str(est), "--quiet"]) == 0
    capsys.readouterr()
    assert (
        main(["plot", str(est), "--input", str(log), "--frame", "5", "--out", str(tmp_path / "p")])
        == 0
    )
    assert len(capsys.readouterr().out.split()) == 4
    assert (
        plot_log(est, __import__("torchcontact").robots.tcarm_path(), tmp_path / "q")[-1].name
        == "quality.png"
    )


def test_plot_errors_are_one_line(model, sim_log, tmp_path, capsys):
    from torchcontact.logs import estimate_file

    est = estimate_file(sim_log, model, tmp_path / "e.parquet")["output"]
    out = str(tmp_path / "p")

    def error(args, code):
        assert main(["plot", *args]) == code
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), err
        return err[0]

    assert "not an output of torchcontact estimate" in error([str(sim_log), "--out", out], 1)
    assert "no such file" in error([str(tmp_path / "none.parquet"), "--out", out], 1)
    assert "--frame 600: the log has rows 0..599" in error(
        [str(est), "--input", str(sim_log), "--frame", "600", "--out", out], 2
    )
    short = tmp_path / "short.parquet"
    pq.write_table(pq.read_table(sim_log).slice(0, 10), short)
    assert "10 rows, the estimate has 600" in error(
        [str(est), "--input", str(short), "--out", out], 1
    )
    other = tmp_path / "other.urdf"
    other.write_text(tcarm_path().read_text().replace("tcarm", "tcarm2"))
    assert "estimated with another robot" in error(
        [str(est), "--robot", str(other), "--out", out], 1
    )


def test_robot_view_defaults_to_a_well_posed_frame(model, tmp_path):
    import numpy as np

    from torchcontact.logs import estimate_file, write_simulated_log
    from torchcontact.logs.plot import _default_frame, _flat_contacts, _rank_deficient

    log = write_simulated_log(model, 2000, tmp_path / "l.parquet", seed=0)  # the demo's log
    est = pq.read_table(estimate_file(log, model, tmp_path / "e.parquet")["output"])
    deficient = _rank_deficient(est, ["base_ft"])
    assert deficient.any()  # two-contact frames: rank 5 of 6 unknowns
    f = _default_frame(est, _flat_contacts(est), deficient)
    assert not deficient[f] and est["status_code"][f].as_py() == 0
    assert len(est["contacts"][f].as_py()) >= 1
    assert np.all(est["rank.base_ft"].to_numpy()[f] == est["unknowns.base_ft"].to_numpy()[f])


def test_nullspace_view_draws_forces_the_sensor_cannot_see(model, tmp_path):
    """The drawn directions are the null space: unit vectors whose contact forces add up to no
    wrench on the sensor (both contacts of the tcarm are behind base_ft), as many as
    ``nullity.base_ft`` says; also on a ``--constraints`` estimate."""
    import numpy as np

    from torchcontact.logs import LogConstraints, estimate_file, write_simulated_log
    from torchcontact.logs.plot import _null_directions, _nullity, _posed

    sim_log = write_simulated_log(model, 2000, tmp_path / "l.parquet", seed=0)  # the demo's log

    out = estimate_file(
        sim_log, model, tmp_path / "e.parquet", constraints=LogConstraints(friction=0.5)
    )["output"]
    est = pq.read_table(out)
    nullity = _nullity(est, ["base_ft"])[:, 0]
    assert np.array_equal(
        nullity, est["unknowns.base_ft"].to_numpy() - est["rank.base_ft"].to_numpy()
    )
    two = int(np.flatnonzero(nullity == 1)[0])  # two pure forces: 6 unknowns, rank 5
    for frame, d in ((two, 1), (int(np.flatnonzero(nullity == 0)[0]), 0)):
        q, fp = _posed(est, model, sim_log, frame)
        dirs, labels, bases = _null_directions(est, model, ["base_ft"], q, fp, frame)
        assert len(dirs) == d and bases["base_ft"].shape == (len(labels["base_ft"]), d)
        np.testing.assert_allclose(bases["base_ft"].T @ bases["base_ft"], np.eye(d), atol=1e-12)
        for _, _, _, parts in dirs:
            force = sum(f for _, f, _ in parts)
            moment = sum(np.cross(c, f) + (0 if m is None else m) for c, f, m in parts)
            np.testing.assert_allclose(force, 0, atol=1e-9)
            np.testing.assert_allclose(moment, 0, atol=1e-9)
            # not trivially zero: opposite forces of norm 1/sqrt(2) along the line through the
            # two points
            (c1, f1, _), (c2, f2, _) = parts
            u = (c1 - c2) / np.linalg.norm(c1 - c2)
            np.testing.assert_allclose(abs(f1 @ u), np.sqrt(0.5), rtol=1e-9)
            np.testing.assert_allclose(f1 + f2, 0, atol=1e-12)
    pngs = plot_log(out, tcarm_path(), tmp_path / "p", input_log=sim_log)
    assert [p.name for p in pngs][-1] == "nullspace.png" and pngs[-1].stat().st_size > 10_000
