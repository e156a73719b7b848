"""The ``torchcontact`` command line: one ``error:`` line per user error (exit 2 usage, 1 data),
tracebacks only with ``--debug``, defaults in the help, and the installed applications."""

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from torchcontact import __version__
from torchcontact.cli import main


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
    assert main(["estimate", str(no_names), "--out", out, "--robot", "tcarm"]) == 1
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
    assert "(default: float32; float64 for --format c)" in capsys.readouterr().out


# ----------------------------------------------------------------------- one robot argument
def _bad_robots(tmp_path):
    """The three bad forms of --robot and what the error line says of each."""
    folder = tmp_path / "folder.urdf"
    folder.mkdir(parents=True)
    sdf = tmp_path / "model.sdf"
    sdf.write_text("<?xml version='1.0'?><sdf version='1.9'><model name='m'/></sdf>")
    return [
        (folder, "a folder, not a URDF file"),
        (tmp_path / "missing.urdf", "no such URDF file"),
        (sdf, "not a URDF file (its root element is <sdf>, not <robot>)"),
    ]


def _robot_commands(tmp_path, log):
    """argv of every command that takes a robot (the robot argument is appended)."""
    return {
        "simulate": ["simulate", "--frames", "5", "--out", tmp_path / "s.parquet"],
        "demo": ["demo", "--frames", "5", "--out", tmp_path / "demo"],
        "estimate": ["estimate", log, "--out", tmp_path / "e.parquet"],
        "plot": ["plot", tmp_path / "e.parquet", "--out", tmp_path / "png"],
        "convert": ["convert", tmp_path / "x.csv", "--out", tmp_path / "c.parquet"],
        "train fit": ["train", "fit", "--out", tmp_path / "ckpt"],
        "train benchmark": ["train", "benchmark", "--out", tmp_path / "bench"],
        "train heldout": ["train", "heldout", "--out", tmp_path / "held"],
        "export estimator": [
            "export",
            "estimator",
            "--slot",
            "hand_skin:force",
            "--out",
            tmp_path / "e.onnx",
        ],  # fmt: skip
        "export residual": ["export", "residual", tmp_path / "ckpt", "--out", tmp_path / "r.onnx"],
        "run": ["run", "--onnx", tmp_path / "e.onnx", "--tcp", "127.0.0.1:1"],
    }


def test_every_command_refuses_a_bad_robot_with_one_line_and_exit_2(small_log, tmp_path, capsys):
    for name, argv in _robot_commands(tmp_path, small_log).items():
        for robot, why in _bad_robots(tmp_path / name.replace(" ", "_")):
            assert main([*map(str, argv), "--robot", str(robot)]) == 2, (name, robot)
            line = _error_line(capsys)
            assert f"--robot {robot}: {why}" in line, (name, line)
    assert not any(tmp_path.glob("*.parquet")) and not any(tmp_path.glob("*.onnx"))


def test_robot_names_tcarm_and_icub(tmp_path, monkeypatch, capsys):
    import icub_models

    from torchcontact.robots import robot_urdf, tcarm_path

    assert robot_urdf("tcarm") == tcarm_path()
    assert robot_urdf("icub") == Path(icub_models.get_model_file("iCubGenova04"))
    out = tmp_path / "icub.parquet"
    assert main(["simulate", "--robot", "icub", "--frames", "3", "--out", str(out), "--quiet"]) == 0
    assert (
        pq.read_schema(out).metadata[b"torchcontact.robot"]
        == b'{"robot": "icub", "ft_sensors": []}'
    )
    capsys.readouterr()
    monkeypatch.setitem(sys.modules, "icub_models", None)  # not installed
    assert main(["simulate", "--robot", "icub", "--frames", "3", "--out", str(out)]) == 2
    assert "--robot icub needs the icub-models package (pip install icub-models)" in _error_line(
        capsys
    )
    assert main(["estimate", str(out), "--out", str(tmp_path / "e.parquet")]) == 2  # the log's
    line = _error_line(capsys)
    assert "recorded for robot icub" in line and "needs the icub-models package" in line


def test_estimate_takes_the_robot_from_the_log_and_never_silently_the_bundled_arm(
    small_log, tmp_path, capsys
):
    # a robot of the user's own: the bundled arm with another hand mass, at a path
    urdf = tmp_path / "arm.urdf"
    text = __import__("torchcontact").robots.tcarm_path().read_text()
    urdf.write_text(text.replace('<mass value="0.8"/>', '<mass value="0.9"/>', 1))
    assert urdf.read_text() != text
    log = tmp_path / "log.parquet"
    assert main(["simulate", "--robot", str(urdf), "--frames", "40", "--out", str(log)]) == 0
    meta = pq.read_schema(log).metadata
    assert json.loads(meta[b"torchcontact.robot"]) == {"robot": str(urdf), "ft_sensors": []}
    est = tmp_path / "est.parquet"
    assert main(["estimate", str(log), "--out", str(est), "--quiet"]) == 0  # no --robot
    capsys.readouterr()
    both = ["estimate", str(log), str(small_log), "--out", str(tmp_path / "both")]
    assert main(both) == 2  # two robots' logs: which one?
    assert "the input logs record different robots" in _error_line(capsys)
    import torchcontact as tc

    assert pq.read_schema(est).metadata[b"torchcontact.urdf_sha256"].decode() == (
        tc.RobotModel.from_urdf(urdf).urdf_sha256
    )
    # the URDF changed since: refused, never the bundled arm instead
    urdf.write_text(urdf.read_text().replace('<mass value="0.9"/>', '<mass value="1.0"/>', 1))
    assert main(["estimate", str(log), "--out", str(tmp_path / "e2.parquet")]) == 2
    line = _error_line(capsys)
    assert "was recorded for robot" in line and "has changed" in line and "give --robot" in line
    urdf.unlink()
    assert main(["estimate", str(log), "--out", str(tmp_path / "e2.parquet")]) == 2
    assert "which is not found here: give --robot" in _error_line(capsys)
    # a log that records no robot
    bare = tmp_path / "bare.parquet"
    tab = pq.read_table(small_log)
    keep = {b"torchcontact.joint_names": tab.schema.metadata[b"torchcontact.joint_names"]}
    pq.write_table(tab.replace_schema_metadata(keep), bare)
    assert main(["estimate", str(bare), "--out", str(tmp_path / "e3.parquet")]) == 2
    assert "records no robot in its metadata: give --robot" in _error_line(capsys)
    assert not (tmp_path / "e2.parquet").exists() and not (tmp_path / "e3.parquet").exists()
    # a log recorded with the bundled arm at a path that no longer exists: found by its hash
    moved = pq.read_table(small_log)
    meta = dict(moved.schema.metadata)
    meta[b"torchcontact.robot"] = b'{"robot": "/gone/tcarm.urdf", "ft_sensors": []}'
    pq.write_table(moved.replace_schema_metadata(meta), tmp_path / "moved.parquet")
    args = ["estimate", str(tmp_path / "moved.parquet"), "--out", str(tmp_path / "e4.parquet")]
    assert main([*args, "--quiet"]) == 0


# ----------------------------------------------------------------------- own robot: --ft-sensor
def test_ft_sensor_on_a_urdf_without_one_simulate_then_estimate(tmp_path, capsys, monkeypatch):
    """The panda of example-robot-data declares no F/T sensor: a wrist sensor on the fixed joint
    carrying the hand, simulated, then estimated with the robot (and sensor) from the log."""
    from robots import erd_path

    import torchcontact as tc
    from torchcontact.robots import load_robot_model

    panda = erd_path("panda_description/urdf/panda.urdf")
    assert not tc.RobotModel.from_urdf(panda).ft_sensors
    # by the link it carries or by the joint; the same sensor as with_ft_sensor's
    a = load_robot_model(panda, ["wrist_ft:panda_hand"]).ft_sensors["wrist_ft"]
    ref = tc.RobotModel.from_urdf(panda, keep_fixed=["panda_hand_joint"])
    b = ref.with_ft_sensor("wrist_ft", "panda_hand_joint").ft_sensors["wrist_ft"]
    assert a.joint == b.joint == "panda_hand_joint"
    np.testing.assert_array_equal(a.R_child_sensor, b.R_child_sensor)
    toml = tmp_path / "sensors.toml"
    toml.write_text('[[ft_sensor]]\nname = "wrist_ft"\njoint = "panda_hand_joint"\n')
    c = load_robot_model(panda, [str(toml)]).ft_sensors["wrist_ft"]
    np.testing.assert_array_equal(c.p_child_sensor, b.p_child_sensor)
    # the example of docs/cli.md, as written there
    import re
    import shlex

    block = re.search(r"```sh\n(pip install example-robot-data.*?)```", ref_text(), re.S).group(1)
    commands = block.replace("\\\n", "").splitlines()  # shell line continuations
    lines = [ln.split("#")[0] for ln in commands if ln.startswith("torchcontact ")]
    assert len(lines) == 3
    monkeypatch.chdir(tmp_path)
    for line in lines:
        argv = shlex.split(line.replace('"$PANDA"', shlex.quote(str(panda))))
        assert main([*argv[1:], "--quiet"] if argv[1] != "export" else argv[1:]) == 0, line
    capsys.readouterr()
    assert "ft.wrist_ft" in pq.read_schema("panda.parquet").names
    tab = pq.read_table("panda_est.parquet")  # estimated without --robot: robot and sensor logged
    assert set(tab["status"].to_pylist()) == {"ok"}
    one = [r[0] for r in tab["contacts"].to_pylist() if len(r) == 1]
    assert len(one) > 40
    np.testing.assert_allclose([c["force"] for c in one], [c["true_force"] for c in one], atol=1e-8)
    assert (tmp_path / "panda.onnx").stat().st_size > 0


def ref_text():
    return (Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()


def test_bad_ft_sensor_specs_are_one_line_exit_2(tmp_path, capsys):
    out = str(tmp_path / "s.parquet")
    sim = ["simulate", "--frames", "3", "--out", out, "--ft-sensor"]
    for spec, why in [
        ("wrist", "expected NAME:JOINT_OR_LINK"),
        ("w:nope", "'nope' is no joint or link of tcarm"),
        ("w:elbow", "joint 'elbow_pitch' is revolute; an F/T sensor sits on a fixed joint"),
        ("base_ft:hand_skin", "tcarm already declares sensor 'base_ft'"),
        ("w:hand_skin:frame=world", "frame=world"),
        ("w:hand_skin:xyz=1,2", "xyz= takes 3 finite numbers"),
        (str(tmp_path / "none.toml"), "no such file"),
    ]:
        assert main([*sim, spec]) == 2, spec
        assert why in _error_line(capsys), spec
    assert main(["convert", "x.csv", "--out", out, "--ft-sensor", "w:hand_skin"]) == 2
    assert "give --robot too" in _error_line(capsys)
    assert not (tmp_path / "s.parquet").exists()


# ----------------------------------------------------------------------- help texts
MARKUP = ("``", ":mod:", ":func:", ":class:", ":meth:", ":data:", ":attr:")


def _cli_reference():
    """docs/cli_reference.py: the walk over every parser, and the writer of docs/cli.md."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "docs" / "cli_reference.py"
    spec = importlib.util.spec_from_file_location("cli_reference", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_docs_cli_md_is_generated_from_the_parsers():
    ref = _cli_reference()
    assert ref.main(["--check"]) == 0, "docs/cli.md is not current: python docs/cli_reference.py"
    text = ref.OUT.read_text()
    for cmd in ("estimate", "simulate", "demo", "plot", "convert", "sensor read", "run",
                "train fit", "export estimator", "export residual"):  # fmt: skip
        assert f"### `torchcontact {cmd}`" in text, cmd
    assert "| `--strict-joints` |" in text and "| 2 | usage error" in text


def test_every_help_shows_its_defaults_and_no_markup(capsys):
    import argparse

    parsers = list(_cli_reference().iter_parsers())
    paths = [" ".join(p) for p, _ in parsers]
    for cmd in ("estimate", "simulate", "demo", "plot", "convert", "sensor read",
                "sensor simulate", "run", "train fit", "train benchmark", "train heldout",
                "train study", "export estimator", "export residual"):  # fmt: skip
        assert cmd in paths, cmd
    undocumented = []
    for path, parser in parsers:
        with pytest.raises(SystemExit) as e:
            main([*path, "--help"])  # the real command line, as a user runs it
        assert e.value.code == 0
        text = capsys.readouterr().out
        assert text.startswith("usage: torchcontact"), path
        bad = [m for m in MARKUP if m in text]
        assert not bad, f"torchcontact {' '.join(path)} --help shows markup {bad}"
        assert "python -m" not in text, f"torchcontact {' '.join(path)} --help: {text}"
        fmt = parser._get_formatter()
        for action in parser._actions:
            flag = isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction))
            if (
                not action.option_strings
                or action.required
                or flag
                or action.default is argparse.SUPPRESS
                or isinstance(action, (argparse._HelpAction, argparse._VersionAction))
            ):
                continue
            if "default" not in (fmt._get_help_string(action) or ""):
                undocumented.append(f"{' '.join(path)} {action.option_strings[0]}")
        # one robot argument: the same forms everywhere, with --ft-sensor beside it
        opts = {o: a for a in parser._actions for o in a.option_strings}
        if "--robot" in opts:
            assert "tcarm (the bundled arm), icub (iCubGenova04" in opts["--robot"].help, path
            assert "--ft-sensor" in opts and "NAME:JOINT_OR_LINK" in opts["--ft-sensor"].help
    assert not undocumented, f"options whose --help shows no default: {undocumented}"
    takes_robot = {" ".join(p) for p, parser in parsers
                   if any("--robot" in a.option_strings for a in parser._actions)}  # fmt: skip
    assert takes_robot >= {"estimate", "simulate", "demo", "plot", "convert", "run", "train fit",
                           "train benchmark", "train heldout", "export estimator",
                           "export residual"}  # fmt: skip


def test_a_missing_optional_dependency_names_its_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "tqdm", None)  # as in an install without the logs extra
    assert main(["simulate", "--frames", "3", "--out", str(tmp_path / "s.parquet")]) == 1
    line = _error_line(capsys)
    assert "needs tqdm, which is not installed: pip install 'torchcontact[logs]'" in line
    assert "unexpected" not in line and not (tmp_path / "s.parquet").exists()


def test_ray_is_shut_down_at_the_end_only_where_this_process_started_it(monkeypatch):
    """The console script's end (``_end_ray``): a local Ray instance this process started ends with it (its head
    processes would outlive it); a running cluster it joined is not shut down (the cluster ends
    the driver's job when the process exits)."""
    import types

    from torchcontact import cli
    from torchcontact.logs import _ray_boot

    calls = []
    fake = types.SimpleNamespace(is_initialized=lambda: True, shutdown=lambda: calls.append(1))
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.setattr(_ray_boot, "_local_instance", [])
    cli._end_ray()  # joined a running cluster
    assert calls == []
    monkeypatch.setattr(_ray_boot, "_local_instance", [True])
    cli._end_ray()  # started here
    assert calls == [1]
    fake.is_initialized = lambda: False
    cli._end_ray()  # not running any more
    assert calls == [1]


def test_the_console_script_ends_at_once_and_loses_nothing(small_log, tmp_path):
    """``console_main`` skips the interpreter's shutdown (no atexit handler runs) once stdout is
    flushed; a stdout it cannot write is an error, not exit 0; ``python -m torchcontact`` keeps
    the normal shutdown. (An estimate through this entry: tests/logs/test_startup.py.)"""
    import subprocess

    import tomllib

    root = Path(__file__).resolve().parents[1]
    scripts = tomllib.loads((root / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["torchcontact"] == "torchcontact.cli:console_main"
    hook = "import atexit; atexit.register(lambda: print('shutdown ran', flush=True))\n"
    entry = hook + "from torchcontact.cli import console_main; console_main()"

    def console(*args, stdout=subprocess.PIPE):
        return subprocess.run([sys.executable, "-c", entry, *args], stdout=stdout,
                              stderr=subprocess.PIPE, text=True, cwd=tmp_path)  # fmt: skip

    r = console("--version")
    assert (r.returncode, r.stdout.strip()) == (0, __version__)  # no 'shutdown ran'
    r = console("estimate", str(small_log))  # --out missing: a usage error
    assert r.returncode == 2 and r.stderr.startswith("error: ") and r.stdout == ""
    with open("/dev/full", "w") as full:  # a full disk under stdout
        r = console("--version", stdout=full)
    assert r.returncode == 1 and "error: standard output: No space left" in r.stderr
    r = subprocess.run([sys.executable, "-c", hook + "import runpy; runpy.run_module("
                        "'torchcontact', run_name='__main__')", "--version"],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 0 and r.stdout.splitlines() == [__version__, "shutdown ran"]
