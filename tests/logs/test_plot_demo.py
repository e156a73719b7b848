import pyarrow.parquet as pq

from torchcontact.cli import main
from torchcontact.logs.plot import plot_log


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
