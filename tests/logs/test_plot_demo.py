import pyarrow.parquet as pq

from torchcontact.cli import main
from torchcontact.logs.plot import plot_log
from torchcontact.robots import tcarm_path


def test_demo_writes_log_estimate_and_pngs(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--frames", "400", "--out", str(out), "--noise", "0.01"]) == 0
    printed = capsys.readouterr().out
    for name in ("log.parquet", "estimate.parquet", "forces.png", "quality.png", "robot.png"):
        assert (out / name).exists() and str(out / name) in printed
        assert (out / name).stat().st_size > 1000
    assert pq.read_table(out / "log.parquet").column_names[-1] == "temperature"


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
    assert len(capsys.readouterr().out.split()) == 3
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
