"""The C step (torchcontact.online.cstep, run by EstimatorRuntime(backend="c")): parity with the
torch estimator in float64, the C program in examples/, the robot identity, bad input, the CLI."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from online_scenes import KINDS, LINKS

import torchcontact as tc
from torchcontact.errors import InputError, ModelMismatchError
from torchcontact.online.estimator import OnlineEstimator
from torchcontact.residual import ResidualCorrection, sensor_regressor, subtree_bodies

ROOT = Path(__file__).resolve().parents[2]
TOL = dict(rtol=0.0, atol=1e-12)  # the bound: C float64 vs torch float64 <= 1e-12 N


def CStepRuntime(path, robot=None, **kw):  # noqa: N802 - the runtime's C backend
    from torchcontact.runtime import EstimatorRuntime

    return EstimatorRuntime(path, robot, backend="c", **kw)


def test_the_c_backend_imports_neither_torch_nor_onnxruntime(arm_lib):
    """EstimatorRuntime(backend="c") steps with numpy and ctypes alone (onnxruntime blocked)."""
    code = (
        "import sys; sys.modules['onnxruntime'] = None;"
        "import numpy as np, torchcontact.online.derivatives;"
        "from torchcontact.runtime import EstimatorRuntime;"
        f"rt = EstimatorRuntime({str(arm_lib[0])!r}, 'tcarm', track_bias=True);"
        "out = rt.step({'q': np.zeros(7), 'qd': np.zeros(7), 'qdd': np.zeros(7),"
        " 'ft': np.zeros((1, 6)), 'active': np.zeros(3)}); rt.tare();"
        "assert out['status'] == 0 and out['bias'].updated[0];"
        "bad = [m for m in ('torch',) if m in sys.modules];"
        "assert not bad, bad"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def _frames(rng, nv, K, n):
    for _ in range(n):
        q, qd, qdd = rng.uniform(-1.5, 1.5, (3, nv))
        yield (q, qd, qdd, rng.normal(0, 10, (1, 6)), rng.uniform(-0.03, 0.03, (K, 3)),
               (rng.random(K) < 0.6).astype(float))  # fmt: skip


def _compare(c, t, rng, nv, K, n=12):
    for frame in _frames(rng, nv, K, n):
        a, b = c.step(*frame), t.step(*frame)
        assert a["status"] == b["status"] == 0
        for key in ("force", "moment", "joint_torques", "residual", "ft_model"):
            np.testing.assert_allclose(a[key], b[key], **TOL, err_msg=key)
        assert a["rank"].tolist() == b["rank"].tolist()
        np.testing.assert_allclose(a["bias"].offset, b["bias"].offset, **TOL)


def test_c_step_equals_the_torch_estimator_float64(arm, arm_lib):
    """Offsets, payload and stack-like inertial change inside; every output to 1e-12."""
    path, meta = arm_lib
    rng = np.random.default_rng(0)
    c = CStepRuntime(path, robot="tcarm", track_bias=True)
    t = OnlineEstimator(arm, None, LINKS, KINDS, track_bias=True, backend="eager")
    for rt in (c, t):  # a tool with an inertia, on the hand
        rt.set_payload(0.7, com=(0.01, 0.02, 0.05), inertia=np.diag([0.01, 0.012, 0.015]))
    _compare(c, t, rng, arm.nv, len(LINKS), 8)
    # the payload body's regressor against torchcontact.residual (tested against pinocchio)
    q, qd, qdd = (torch.as_tensor(rng.uniform(-1, 1, (1, arm.nv))) for _ in range(3))
    c.step(q[0].numpy(), qd[0].numpy(), qdd[0].numpy(), np.zeros((1, 6)))
    body = arm.frame(meta["online"][0]["payload_link"]).body
    Y = sensor_regressor(arm, "base_ft", q, qd, qdd, [body])[0].numpy()
    np.testing.assert_allclose(c.backend.output("regressor.base_ft"), Y, **TOL)
    # batched: run() equals step() frame by frame (the payload in both)
    frames = {"q": rng.uniform(-1, 1, (3, arm.nv)), "qd": rng.uniform(-1, 1, (3, arm.nv)),
              "qdd": np.zeros((3, arm.nv)), "ft": rng.normal(0, 5, (3, 1, 6)),
              "positions": rng.uniform(-0.03, 0.03, (3, 3, 3))}  # fmt: skip
    out = c.run(frames)
    assert out["force"].shape == (3, 3, 3) and out["status"].tolist() == [0, 0, 0]
    for i in range(3):
        one = c.step({k: v[i] for k, v in frames.items()})
        np.testing.assert_allclose(out["force"][i], one["force"], rtol=0, atol=0)
        np.testing.assert_allclose(out["ft_model"][i], one["ft_model"], rtol=0, atol=0)


def test_c_step_with_a_correction_stack_on_icub(tmp_path):
    """iCub's left arm sensor, 4 slots, the stack's offset and inertial layers in the library."""
    from online_scenes import icub_model

    from torchcontact.online.cstep import export_c_step

    m = icub_model()
    bodies = tuple(m.body_names[b] for b in subtree_bodies(m, "l_arm_ft"))
    gen = torch.Generator().manual_seed(1)
    stack = ResidualCorrection(
        m, "l_arm_ft", offset=torch.randn(6, dtype=torch.float64, generator=gen),
        inertial_bodies=bodies[-2:],
        delta=0.02 * torch.randn(20, dtype=torch.float64, generator=gen),
    ).save(tmp_path / "ckpt")  # fmt: skip
    links = ("l_hand", "l_hand", "l_forearm", "l_forearm")
    kinds = ("force", "force", "force", "wrench")
    path = tmp_path / "icub.so"
    meta = export_c_step(m, ["l_arm_ft"], links, kinds, path, correction=stack, joints="sensed")
    assert meta["correction"]["l_arm_ft"]["in_library"] == ["offset", "inertial"]
    c = CStepRuntime(path, robot=m)
    t = OnlineEstimator(m, ["l_arm_ft"], links, kinds, correction=stack, backend="eager")
    np.testing.assert_allclose(c.online.state.bias(), t.state.bias(), rtol=0, atol=0)
    rng = np.random.default_rng(3)
    torques = [m.joint_names.index(j) for j in meta["torque_joints"]]
    for frame in _frames(rng, m.nv, 4, 6):
        a, b = c.step(*frame), t.step(*frame)
        assert a["status"] == b["status"] == 0
        for key in ("force", "moment", "residual", "ft_model"):
            np.testing.assert_allclose(a[key], b[key], **TOL, err_msg=key)
        np.testing.assert_allclose(a["joint_torques"][torques], b["joint_torques"][torques], **TOL)
        assert np.isnan(np.delete(a["joint_torques"], torques)).all()


def test_status_bits_and_nan_outputs(arm_lib):
    c = CStepRuntime(arm_lib[0], track_bias=True)
    q = np.zeros(7)
    out = c.step([np.nan] + [0.0] * 6, q, q, np.zeros((1, 6)), active=np.zeros(3))
    assert out["status"] == 2 and np.isnan(out["force"]).all() and np.isnan(out["ft_model"]).all()
    assert not out["bias"].updated[0]  # a bad frame never updates the offset
    out = c.step(q, q, q, np.full((1, 6), np.inf), active=np.zeros(3))
    assert out["status"] == 1
    with pytest.raises(InputError, match=r"q must have shape \(7,\)"):
        c.step(np.zeros(6), q, q, np.zeros((1, 6)))
    with pytest.raises(InputError, match=r"ft must have shape \(1, 6\)"):
        c.step(q, q, q, np.zeros(5))
    with pytest.raises(InputError, match="no input 'omega'"):
        c.step(q, q, q, np.zeros((1, 6)), omega=np.zeros(3))


def test_refuses_another_robot_or_layout(arm_lib, tmp_path):
    from robots import erd_path

    path = arm_lib[0]
    with pytest.raises(ModelMismatchError, match="exported for robot 'tcarm'"):
        CStepRuntime(path, robot=erd_path("panda_description/urdf/panda.urdf"))
    with pytest.raises(ModelMismatchError, match="expects joints"):
        CStepRuntime(path, expect_joint_names=["a"] * 7)
    with pytest.raises(ModelMismatchError, match="contact slots"):
        CStepRuntime(path, expect_slots=(["hand_skin"], ["force"]))
    with pytest.raises(ModelMismatchError, match="prefix 'other'"):
        CStepRuntime(path, prefix="other")
    with pytest.raises(InputError, match="no such file"):
        CStepRuntime(tmp_path / "missing.so")
    (tmp_path / "junk.so").write_bytes(b"not a library")
    with pytest.raises(ModelMismatchError, match="not a torchcontact C step"):
        CStepRuntime(tmp_path / "junk.so")


def test_tare_and_payload_commands(arm_lib):
    c = CStepRuntime(arm_lib[0], robot="tcarm")
    q = np.full(7, 0.3)
    with pytest.raises(InputError, match="needs a frame first"):
        c.tare()
    out = c.step(q, q * 0, q * 0, np.ones((1, 6)), active=[0.0, 1.0, 0.0])
    with pytest.raises(InputError, match="contact is active on sensor.*base_ft"):
        c.tare()
    out = c.step(q, q * 0, q * 0, np.ones((1, 6)), active=np.zeros(3))
    s = c.tare()  # at this pose, from the model: the reading less the model's prediction
    np.testing.assert_allclose(s.offset[0], 1.0 - out["ft_model"][0], **TOL)
    with pytest.raises(InputError, match="triangle inequality"):
        c.set_payload(1.0, inertia=np.diag([1.0, 0.1, 0.1]))
    with pytest.raises(InputError, match="not carried by sensor"):
        c.set_payload(1.0, link="no_such_link")
    with pytest.raises(InputError, match="start_identification"):
        c.identify_payload()
    before = c.step(q, q * 0, q * 0, np.ones((1, 6)), active=np.zeros(3))["ft_model"]
    c.set_payload(0.5, com=(0, 0, 0.1))
    after = c.step(q, q * 0, q * 0, np.ones((1, 6)), active=np.zeros(3))["ft_model"]
    assert abs(np.linalg.norm(after[0, :3] - before[0, :3]) - 0.5 * 9.81) < 1e-9  # its weight


def test_the_c_program_in_examples(arm_lib, tmp_path):
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.fail("no C compiler: the C step needs one (gcc or clang)")
    path, meta = arm_lib
    exe = tmp_path / "c_step"
    subprocess.run(
        [cc, "-O2", "-Wall", "-Werror", "-include", str(path.with_suffix(".h")),
         str(ROOT / "examples" / "c_step.c"), str(path), f"-Wl,-rpath,{path.parent}", "-lm",
         "-o", str(exe)], check=True, capture_output=True, text=True,
    )  # fmt: skip
    c = CStepRuntime(path)
    rng = np.random.default_rng(5)
    x = c.backend.pack(4, q=rng.uniform(-1, 1, (4, 7)), qd=rng.uniform(-1, 1, (4, 7)),
               ft=rng.normal(0, 5, (4, 1, 6)), positions=rng.uniform(-0.03, 0.03, (4, 3, 3)),
               active=[[1, 0, 1], [0, 1, 0], [1, 1, 1], [0, 0, 0]])  # fmt: skip
    x[2, meta["inputs"]["qdd"][0]] = np.nan  # a bad frame: status 2 from C too
    text = "\n".join(" ".join(repr(float(v)) for v in row) for row in x)
    r = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True)
    rows = np.array([[float(v) for v in line.split()] for line in r.stdout.splitlines()])
    ref = c.backend.run(x)
    assert rows[:, 0].tolist() == [0, 0, 2, 0]
    np.testing.assert_array_equal(rows[:, 1:], ref)  # same library, same bits
    meta_c = json.loads(subprocess.run([str(exe), "--meta"], capture_output=True, text=True,
                                       check=True).stdout)  # fmt: skip
    assert meta_c["urdf_sha256"] == tc.RobotModel.from_urdf(tc.robots.tcarm_path()).urdf_sha256
    bench = subprocess.run([str(exe), "--bench", "2000"], input="", capture_output=True,
                           text=True, check=True).stdout.split()  # fmt: skip
    assert bench[0] == "p50_ns" and int(bench[1]) > 0 and bench[-1] == "0"


def test_cli_format_c(tmp_path, capsys):
    from export.__main__ import main

    out = tmp_path / "arm.so"
    argv = ["estimator", "--robot", "tcarm", "--slot", "hand_skin:force", "--format", "c",
            "--joints", "sensed", "--no-build", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["header"] == str(tmp_path / "arm.h") and not out.exists()
    header = (tmp_path / "arm.h").read_text()
    assert "int tc_estimator_step(const tc_estimator_real* x, tc_estimator_real* out);" in header
    assert json.loads((tmp_path / "arm.json").read_text())["format"] == "torchcontact.cstep/1"
    assert main(["estimator", "--robot", "tcarm", "--slot", "hand_skin:force", "--format", "c",
                 "--out", str(tmp_path / "x.onnx")]) == 2  # fmt: skip
    assert "--out NAME.so" in capsys.readouterr().err
    assert main(argv[:-1] + [str(tmp_path / "y.so"), "--constraints"]) == 2
    assert main(argv[:-1] + [str(tmp_path / "z.so"), "--prefix", "9bad"]) == 2
