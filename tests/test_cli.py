"""The ``torchcontact`` command line: one ``error:`` line per user error (exit 2 usage, 1 data),
tracebacks only with ``--debug``, defaults in the help, and the installed applications."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import torch

from torchcontact import __version__
from torchcontact.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == __version__


def _error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    import torchcontact as tc
    from torchcontact.logs import write_simulated_log

    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    return write_simulated_log(model, 120, tmp_path_factory.mktemp("cli") / "log.parquet", seed=1)


def test_usage_errors_are_one_line_with_exit_2(small_log, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["estimate", str(small_log)])  # --out missing
    assert e.value.code == 2 and "--out" in _error_line(capsys)
    out = tmp_path / "o.parquet"
    assert main(["estimate", str(small_log), "--out", str(out), "--batch-size", "0"]) == 2
    assert "--batch-size must be an integer >= 1" in _error_line(capsys)
    assert list(tmp_path.iterdir()) == []  # no .partial left to block the rerun
    assert main(["estimate", str(small_log), "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["simulate", "--frames", "0", "--out", str(tmp_path / "s.parquet")]) == 2
    assert "--frames must be >= 1" in _error_line(capsys)
    assert main(["estimate", str(small_log), "--out", str(out), "--workers", "2"]) == 2
    assert "--workers applies to --engine ray" in _error_line(capsys)
    assert main(["estimate", str(small_log), "--out", str(out), "--ft-range", "x"]) == 2
    assert "--ft-range x: expected SENSOR=LIMIT" in _error_line(capsys)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_device_cuda_without_cuda(small_log, tmp_path, capsys):
    out = tmp_path / "o.parquet"
    assert main(["estimate", str(small_log), "--out", str(out), "--device", "cuda"]) == 2
    assert "--device cuda: CUDA is not available" in _error_line(capsys)
    assert not out.exists() and not (tmp_path / "o.parquet.partial").exists()


def test_output_that_is_an_input_is_refused(small_log, tmp_path, capsys):
    before = small_log.read_bytes()
    assert main(["estimate", str(small_log), "--out", str(small_log)]) == 2
    assert "is the input" in _error_line(capsys) and small_log.read_bytes() == before
    urdf = tmp_path / "arm.urdf"
    shutil.copy(__import__("torchcontact").robots.tcarm_path(), urdf)
    assert main(["simulate", "--robot", str(urdf), "--frames", "10", "--out", str(urdf)]) == 2
    assert "is the input" in _error_line(capsys)
    assert urdf.read_text().startswith("<?xml")


def test_data_errors_are_one_line_with_exit_1(small_log, tmp_path, capsys):
    bad_urdf = tmp_path / "bad.urdf"
    bad_urdf.write_text("<robot name='x'><link name='a'/><joint name='j' type='warp'/></robot>")
    out = str(tmp_path / "o.parquet")
    assert main(["estimate", str(small_log), "--out", out, "--robot", str(bad_urdf)]) == 1
    assert "bad.urdf" in _error_line(capsys)
    no_names = tmp_path / "no_names.parquet"
    pq.write_table(pq.read_table(small_log).replace_schema_metadata(None), no_names)
    assert main(["estimate", str(no_names), "--out", out]) == 1
    assert "no_names.parquet: no joint names" in _error_line(capsys)
    assert main(["estimate", str(tmp_path / "none.parquet"), "--out", out]) == 1
    assert "none.parquet: no such file" in _error_line(capsys)
    assert main(["estimate", str(small_log), "--out", out, "--robot", "missing.urdf"]) == 2
    assert "--robot missing.urdf: no such URDF file" in _error_line(capsys)


def test_debug_shows_the_traceback(small_log, tmp_path, capsys):
    out = str(tmp_path / "o.parquet")
    assert main(["estimate", str(small_log), "--out", out, "--batch-size", "0", "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and err.rstrip().splitlines()[-1].startswith(
        "error: --batch-size"
    )


def test_warnings_are_lines(small_log, tmp_path, capsys):
    nc = tmp_path / "nc.parquet"
    pq.write_table(pq.read_table(small_log).drop_columns(["contacts"]), nc)
    out = tmp_path / "o.parquet"
    assert main(["estimate", str(nc), "--out", str(out), "--batch-size", "16", "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: ") and "no 'contacts' column" in err[0]


def test_help_shows_defaults_and_every_command(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for cmd in ("estimate", "simulate", "demo", "plot", "convert", "sensor", "run", "train",
                "export"):  # fmt: skip
        assert cmd in text
    with pytest.raises(SystemExit):
        main(["estimate", "--help"])
    text = capsys.readouterr().out
    assert "(default: 8192)" in text and "(default: 2.0)" in text
    with pytest.raises(SystemExit):
        main(["train", "fit", "--help"])
    assert "(default: cpu)" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["export", "estimator", "--help"])
    assert "(default: float32)" in capsys.readouterr().out


TINY_CONFIG = """
[data]
frames = 1200
block_seconds = 1.0
[model]
kind = "mlp"
hidden = 8
layers = 1
[train]
epochs = 2
"""


def test_non_editable_install_runs_train_and_export_from_any_directory(tmp_path):
    """``pip install .`` (not editable) into a fresh venv (system site-packages for torch and
    the other dependencies), then the console script from a folder outside the repository."""
    src = tmp_path / "src"
    shutil.copytree(
        ROOT,
        src,
        ignore=shutil.ignore_patterns(
            ".git", "build", "dist", "*.egg-info", "__pycache__", ".*_cache", "*.parquet", "out"
        ),
    )
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    py, exe = venv / "bin" / "python", venv / "bin" / "torchcontact"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    r = subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "--no-deps", str(src)],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    work = tmp_path / "elsewhere"
    work.mkdir()

    def run(*args):
        res = subprocess.run(
            [str(exe), *args], capture_output=True, text=True, cwd=work, env=env, timeout=300
        )
        assert res.returncode == 0, res.stderr[-3000:]
        return res.stdout

    where = subprocess.run(
        [str(py), "-c", "import torchcontact.apps.training as t, torchcontact as c;"
         " print(c.__file__); print(t.__file__)"],
        capture_output=True, text=True, cwd=work, env=env, check=True,
    ).stdout.split()  # fmt: skip
    assert all(str(venv) in w for w in where), where  # the installed copy, not the checkout
    assert "train" in run("--help") and "export" in run("--help")
    (work / "tiny.toml").write_text(TINY_CONFIG)
    run("train", "fit", "--config", "tiny.toml", "--out", "ckpt")
    assert json.loads((work / "ckpt" / "checkpoint.json").read_text())["sensor"] == "base_ft"
    meta = json.loads(run("export", "residual", "ckpt", "--out", "residual.onnx"))
    assert meta["path"] == "residual.onnx" and (work / "residual.onnx").stat().st_size > 0
    run("export", "estimator", "--robot", "tcarm", "--slot", "hand_skin:force", "--out", "e.onnx")
    assert (work / "e.onnx").stat().st_size > 0
