"""Generated kernels (torchcontact.kernels) against the eager program and the references.

Every backend runs the same physics program (torchcontact._scalar); the compiled CPU kernel must
agree with eager torch to rounding (1e-12 on these scenes; FMA contraction is the only difference)
and with pinocchio/iDynTree to the project's 1e-9. Kernels are built into the user cache
(~/.cache/torchcontact, or $TORCHCONTACT_CACHE); tests that check building itself use a
temporary cache.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from robots import ROBOTS, TOL, PinRobot, load_model, random_state

import torchcontact as tc
from torchcontact import dynamics, kernels
from torchcontact.errors import KernelBuildError
from torchcontact.estimation import programs

KERNEL_VS_EAGER = 1e-12  # same program, same rounding but for fused multiply-adds


@pytest.mark.parametrize("name", ["panda", "icub"])
def test_rnea_kernel_matches_pinocchio_and_eager(name):
    model = load_model(name)
    ref = PinRobot(ROBOTS[name](), model)
    q, qd, qdd = random_state(model, 37, seed=1)  # 37: not a multiple of the vector width
    tau = model.inverse_dynamics(q, qd, qdd, backend="cpu")
    eager = model.inverse_dynamics(q, qd, qdd, backend="eager")
    torch.testing.assert_close(tau, eager, atol=KERNEL_VS_EAGER, rtol=0)
    expected = np.stack([ref.rnea(*(x[k].numpy() for x in (q, qd, qdd))) for k in range(37)])
    np.testing.assert_allclose(tau.numpy(), expected, **TOL[torch.float64])


@pytest.mark.parametrize("n", [1, 3, 4, 5, 8, 13])
def test_partial_blocks_and_strided_inputs(n):
    model = load_model("ur5")
    q, qd, qdd = random_state(model, n, seed=2)
    # strided views (every other column of a wider tensor) are read in place
    wide = torch.zeros(n, 2 * model.nv, dtype=torch.float64)
    wide[:, ::2] = q
    qs = wide[:, ::2]
    assert not qs.is_contiguous()
    tau = model.inverse_dynamics(qs, qd, qdd, backend="cpu")
    torch.testing.assert_close(
        tau, model.inverse_dynamics(q, qd, qdd, backend="eager"), atol=KERNEL_VS_EAGER, rtol=0
    )


def test_sincos_in_kernel_large_angles_and_float32():
    """In-kernel sin/cos: exact range reduction up to ~6.6e6 rad (float64), libm beyond."""
    model = tc.RobotModel.from_urdf(io.StringIO(tc.robots.pendulum_urdf()))
    q = torch.tensor(
        [[0.0], [0.3], [-2.0], [1e3], [1e6], [-6e6], [1e9], [3e15]], dtype=torch.float64
    )
    z = torch.zeros_like(q)
    tau = model.inverse_dynamics(q, z, z, backend="cpu")[:, 0]
    # tau = m g l/2 cos(q) for the horizontal-at-zero pendulum about y
    expected = 4.905 * torch.cos(q[:, 0])
    torch.testing.assert_close(tau, expected, atol=1e-13, rtol=0)
    m32 = model.to(dtype=torch.float32)
    q32 = torch.linspace(-3000, 3000, 1001, dtype=torch.float32).unsqueeze(-1)
    z32 = torch.zeros_like(q32)
    t32 = m32.inverse_dynamics(q32, z32, z32, backend="cpu")[:, 0]
    ref = 4.905 * torch.cos(q32.double()[:, 0])
    assert (t32.double() - ref).abs().max() < 5e-6 * 4.905


def test_float32_kernel_relative_to_float64():
    model64, model32 = load_model("icub"), load_model("icub", torch.float32)
    q, qd, qdd = random_state(model64, 64, seed=3)
    ref = model64.inverse_dynamics(q, qd, qdd)
    out = model32.inverse_dynamics(q.float(), qd.float(), qdd.float(), backend="cpu")
    assert out.dtype == torch.float32
    assert (out.double() - ref).abs().max() <= TOL[torch.float32]["rel"] * ref.abs().max()


def test_moving_base_and_external_wrenches_in_kernel():
    model = load_model("xarm7")
    q, qd, qdd = random_state(model, 9, seed=4)
    g = torch.Generator().manual_seed(5)
    base = tc.BaseMotion(*(torch.randn(9, 3, generator=g, dtype=torch.float64) for _ in range(3)))
    f_ext = torch.randn(9, model.nb, 6, generator=g, dtype=torch.float64)
    a = model.inverse_dynamics(q, qd, qdd, base=base, f_ext=f_ext, backend="cpu")
    b = model.inverse_dynamics(q, qd, qdd, base=base, f_ext=f_ext, backend="eager")
    torch.testing.assert_close(a, b, atol=KERNEL_VS_EAGER, rtol=0)


def test_forward_pass_kernel_equals_eager():
    model = load_model("panda")
    q, qd, qdd = random_state(model, 6, seed=6)
    a = model.forward_pass(q, qd, qdd, backend="cpu")
    b = model.forward_pass(q, qd, qdd, backend="eager")
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x, y, atol=KERNEL_VS_EAGER, rtol=0)


ESTIMATE_LINKS = ["l_hand", "l_hand", "l_forearm", "l_forearm", "r_hand", "r_forearm", "l_foot"]
ESTIMATE_KINDS = ["wrench", "force", "force_dir", "known", "force", "force_dir", "force"]


@pytest.mark.parametrize("flags", ["plain", "moving base + torque rows + covariance"])
def test_estimator_kernel_equals_eager_on_every_output(flags):
    model = load_model("icub")
    links, kinds = ESTIMATE_LINKS, ESTIMATE_KINDS
    est = tc.ContactEstimator(model)
    if flags != "plain":
        # the left arm's region only: every contact kind, the base motion, torque rows and the
        # covariance through a kernel a third the size of the whole robot's (build time is the
        # suite's budget); the whole robot's kernel is the "plain" case
        links, kinds = ESTIMATE_LINKS[:4] + ["l_hand"], ESTIMATE_KINDS[:4] + ["force"]
        est = tc.ContactEstimator(model, ["l_arm_ft"])
    n, K = 29, len(links)
    q, qd, qdd = random_state(model, n, seed=7)
    g = torch.Generator().manual_seed(8)
    pos = torch.randn(n, K, 3, generator=g, dtype=torch.float64) * 0.05
    dirs = torch.randn(n, K, 3, generator=g, dtype=torch.float64)
    wr = torch.randn(n, K, 6, generator=g, dtype=torch.float64)
    active = torch.rand(n, K, generator=g) > 0.3
    ft = {s: torch.randn(n, 6, generator=g, dtype=torch.float64) * 20 for s in est.sensor_names}
    ft["l_arm_ft"][3, 2] = float("nan")  # a bad frame: status 1, NaN outputs in both
    dirs[5, 2] = 0.0  # a zero direction: status 8 when slot 2 is active
    kw = {}
    if flags != "plain":
        kw = {
            "base": tc.BaseMotion(
                *(torch.randn(n, 3, generator=g, dtype=torch.float64) for _ in range(3))
            ),  # fmt: skip
            "tau_measured": torch.randn(n, model.nv, generator=g, dtype=torch.float64),
            "tau_mask": torch.tensor(
                [j.startswith(("l_elbow", "l_wrist")) for j in model.joint_names]
            ),  # fmt: skip
            "ft_covariance": {s: torch.eye(6, dtype=torch.float64) * 0.1 for s in est.sensor_names},
            # unweighted: the weighted kernel is tested on the two arm regions
            # (test_estimation_idyntree.py) and on the bundled arm (test_constrained.py)
            "weighted": False,
        }
    c = tc.Contacts(links, kinds, pos, dirs, wr, active)
    a = est.estimate(q, qd, qdd, ft, c, backend="cpu", **kw)
    b = est.estimate(q, qd, qdd, ft, c, backend="eager", **kw)
    assert a.status[3] & 1 and torch.equal(a.status, b.status)
    assert (a.status == 0).sum() > n // 2
    for x, y in zip(a, b, strict=True):
        if isinstance(x, dict):
            for s in x:
                torch.testing.assert_close(x[s], y[s], atol=1e-9, rtol=0, equal_nan=True)
        elif x is not None:
            # rank-deficient frames (minimum-norm solutions) amplify the FMA rounding differences
            torch.testing.assert_close(x, y, atol=1e-9, rtol=1e-9, equal_nan=True)


def test_predict_kernel_equals_eager():
    model = load_model("icub")
    est = tc.ContactEstimator(model)
    n = 11
    q, qd, qdd = random_state(model, n, seed=9)
    g = torch.Generator().manual_seed(10)
    links = ["l_hand", "r_foot", "root_link"]
    pos = torch.randn(n, 3, 3, generator=g, dtype=torch.float64) * 0.05
    wr = torch.randn(n, 3, 6, generator=g, dtype=torch.float64)
    with pytest.raises(ValueError, match="outside every F/T sensor"):
        est.predict_ft(q, qd, qdd, tc.Contacts(links, ["known"] * 3, pos, wrenches=wr))
    links = ["l_hand", "r_foot", "r_upper_leg"]
    c = tc.Contacts(links, ["known"] * 3, pos, wrenches=wr)
    a = est.predict_ft(q, qd, qdd, c, backend="cpu")
    b = est.predict_ft(q, qd, qdd, c, backend="eager")
    for s in a:
        torch.testing.assert_close(a[s], b[s], atol=KERNEL_VS_EAGER, rtol=0)


# ---------------------------------------------------------------------------- building and cache
def _pendulum():
    return tc.RobotModel.from_urdf(io.StringIO(tc.robots.pendulum_urdf(length=0.7)))


def test_build_failure_falls_back_to_eager_with_one_warning(monkeypatch, tmp_path):
    """A kernel whose build failed: ``auto`` runs eagerly with no second warning. The tape VM
    is off here: without a compiler it cannot be built either, and whether this process loaded
    one from an earlier test's cache must not decide the test (test_kernels_vm.py covers it)."""
    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    monkeypatch.setenv("TORCHCONTACT_VM", "0")
    model = _pendulum().with_gravity((0.0, 0.0, -9.5))  # a program no other test built
    q = torch.rand(kernels.AUTO_BUILD_MIN_FRAMES, 1, dtype=torch.float64)
    with pytest.raises(KernelBuildError, match="failed"):
        model.inverse_dynamics(q, q, q, backend="cpu")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tau = model.inverse_dynamics(q, q, q)  # auto: eager, no second warning, no crash
    assert not [w for w in caught if "kernel" in str(w.message)]
    torch.testing.assert_close(tau, model.inverse_dynamics(q, q, q, backend="eager"))


def test_auto_builds_in_the_background_then_uses_the_kernel(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    model = _pendulum().with_gravity((0.0, 0.0, -9.7))
    prog = dynamics.program(model, "id", False, False)
    q = torch.rand(kernels.AUTO_BUILD_MIN_FRAMES, 1, dtype=torch.float64)
    first = model.inverse_dynamics(q, q, q)  # eager now; a detached process builds the kernel
    kernels.wait_for_builds(timeout=300)
    assert list(tmp_path.glob("kernels/tck_rnea_*/*.so"))
    torch.testing.assert_close(model.inverse_dynamics(q, q, q), first, atol=1e-12, rtol=0)
    assert kernels._ready(prog, q)  # the second call loaded and used it


def test_a_background_build_outlives_its_process(tmp_path):
    """A short run starts the build and exits; the build still fills the cache."""
    env = {**os.environ, "TORCHCONTACT_CACHE": str(tmp_path)}
    code = (
        "import io, torch, torchcontact as tc\n"
        "m = tc.RobotModel.from_urdf(io.StringIO(tc.robots.pendulum_urdf(length=0.4)))\n"
        "q = torch.rand(4096, 1, dtype=torch.float64)\n"
        "m.inverse_dynamics(q, q, q)\n"  # eager; the build starts and this process exits
    )
    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, "-c", code], env=env, cwd=root, check=True)
    for _ in range(600):
        if list(tmp_path.glob("kernels/tck_rnea_*/*.so")):
            break
        time.sleep(0.5)
    assert list(tmp_path.glob("kernels/tck_rnea_*/*.so"))


def test_a_killed_build_does_not_block_the_next(monkeypatch, tmp_path):
    """A build killed part-way leaves torch's ``lock`` baton; the next build clears it."""
    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    model = _pendulum().with_gravity((0.0, 0.0, -9.6))
    prog = dynamics.program(model, "id", False, False)
    src, h = kernels._source(prog, torch.float64)
    name, cpp, so = kernels._paths(prog, h)
    kernels._store.write_source(cpp, src)
    (cpp.parent / "lock").write_text("")  # what a SIGKILLed cpp_extension.load leaves behind
    code = f"from pathlib import Path; from torchcontact.kernels import build_source; " \
           f"build_source({name!r}, Path({str(cpp)!r}))"  # fmt: skip
    # in a child process, so that a regression hangs there and fails on the timeout
    kernel = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1],
                            timeout=240, capture_output=True, text=True, check=False)  # fmt: skip
    assert kernel.returncode == 0, kernel.stderr[-2000:]
    assert so.exists() and not (cpp.parent / "lock").exists()
    q = torch.rand(64, 1, dtype=torch.float64)
    torch.testing.assert_close(
        model.inverse_dynamics(q, q, q, backend="cpu"),
        model.inverse_dynamics(q, q, q, backend="eager"), atol=KERNEL_VS_EAGER, rtol=0,
    )  # fmt: skip


def test_disk_cache_makes_a_second_process_start_fast(tmp_path):
    env = {**os.environ, "TORCHCONTACT_CACHE": str(tmp_path)}
    code = (
        "import io, time, torch, torchcontact as tc\n"
        "from torchcontact import dynamics, kernels\n"
        "m = tc.RobotModel.from_urdf(io.StringIO(tc.robots.pendulum_urdf(length=0.3)))\n"
        "t = time.perf_counter()\n"
        "kernels.compiled(dynamics.program(m, 'id', False, False), torch.float64)\n"
        "print(time.perf_counter() - t)\n"
    )
    root = Path(__file__).resolve().parents[1]
    run = [sys.executable, "-c", code]
    cold = float(subprocess.run(run, env=env, cwd=root, capture_output=True, text=True,
                                check=True).stdout)  # fmt: skip
    warm = float(subprocess.run(run, env=env, cwd=root, capture_output=True, text=True,
                                check=True).stdout)  # fmt: skip
    assert warm < 1.0 and warm < cold, (cold, warm)


def test_estimator_programs_share_one_source():
    """The exported, eager and compiled paths run one program: same node set per layout."""
    est = tc.ContactEstimator(tc.RobotModel.from_urdf(tc.robots.tcarm_path()))
    em = est.layout(["hand_skin"], ["force"])
    p1 = programs.program(em, "estimate", False, False, False)
    assert programs.program(em, "estimate", False, False, False) is p1  # cached per layout
    tr, out = p1.trace()
    assert set(out) == {"force", "moment", "tau", "rank", "unknowns", "residual", "status"}
    assert {n.op for n in tr.nodes} <= {"in", "add", "sub", "mul", "div", "neg", "sqrt", "sin",
                                        "cos", "gt", "finite", "and", "or", "not", "sel"}  # fmt: skip


@pytest.mark.skipif(
    not torch.cuda.is_available() and not os.path.exists("/usr/local/cuda/bin/nvcc"),
    reason="needs nvcc",
)
def test_cuda_source_compiles_with_nvcc(tmp_path):
    """Without a GPU the generated CUDA is at least compiled (sm_80) to catch codegen errors."""
    from torchcontact.kernels import _cuda

    model = load_model("ur5")
    src = _cuda.source(dynamics.program(model, "id", True, True), torch.float64)
    cu = tmp_path / "k.cu"
    cu.write_text(src)
    nvcc = "nvcc" if torch.cuda.is_available() else "/usr/local/cuda/bin/nvcc"
    r = subprocess.run([nvcc, "-c", "-arch=sm_80", str(cu), "-o", str(tmp_path / "k.o")],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]


@pytest.mark.skipif(
    not torch.cuda.is_available() and not os.path.exists("/usr/local/cuda/bin/nvcc"),
    reason="needs nvcc",
)
def test_weighted_cuda_source_compiles_with_nvcc(tmp_path):
    """The noise-weighted solve (whitening, its Cholesky factors) in the generated CUDA.

    The constrained, covariance and torque-row programs add code the CPU kernels run from the
    same trace; compiling one here took 4 to 6 min (nvcc on a shared 2-core machine), so only the
    weighted solve is checked.
    """
    from torchcontact.kernels import _cuda

    est = tc.ContactEstimator(tc.RobotModel.from_urdf(tc.robots.tcarm_path()))
    em = est.layout(["forearm_skin", "hand_skin"], ["force", "force"])
    prog = programs.program(em, "estimate", False, False, False, None, False, False, True)
    src = _cuda.source(prog, torch.float64)
    cu = tmp_path / "k.cu"
    cu.write_text(src)
    nvcc = "nvcc" if torch.cuda.is_available() else "/usr/local/cuda/bin/nvcc"
    r = subprocess.run([nvcc, "-c", "-arch=sm_80", str(cu), "-o", str(tmp_path / "k.o")],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_weighted_cuda_kernel_matches_eager():
    model = load_model("icub")
    est = tc.ContactEstimator(model.to("cuda"), ["l_arm_ft"])
    n = 500
    q, qd, qdd = (x.cuda() for x in random_state(model, n, seed=12))
    g = torch.Generator().manual_seed(13)
    pos = (torch.randn(n, 2, 3, generator=g, dtype=torch.float64) * 0.05).cuda()
    nrm = torch.randn(n, 2, 3, generator=g, dtype=torch.float64).cuda()
    c = tc.Contacts(["l_forearm", "l_hand"], ["force", "force"], pos, normals=nrm, cone_angle=0.5)
    ft = {"l_arm_ft": (torch.randn(n, 6, generator=g, dtype=torch.float64) * 5).cuda()}
    cov = {"l_arm_ft": torch.diag(torch.tensor([0.01] * 3 + [2.5e-5] * 3, dtype=torch.float64))}
    for kw in ({}, {"constraints": tc.FrictionCones()}):
        a = est.estimate(q, qd, qdd, ft, c, ft_covariance={k: v.cuda() for k, v in cov.items()},
                         backend="cuda", **kw)  # fmt: skip
        b = est.estimate(q, qd, qdd, ft, c, ft_covariance={k: v.cuda() for k, v in cov.items()},
                         backend="eager", **kw)  # fmt: skip
        torch.testing.assert_close(a.force, b.force, atol=1e-7, rtol=1e-7)
        assert torch.equal(a.status, b.status)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cuda_kernels_match_cpu(dtype):
    model = load_model("icub", dtype)
    q, qd, qdd = (x.to(dtype) for x in random_state(model, 1000, seed=11))
    cpu = model.inverse_dynamics(q, qd, qdd, backend="eager")
    gpu = model.to("cuda").inverse_dynamics(q.cuda(), qd.cuda(), qdd.cuda(), backend="cuda")
    tol = 1e-9 if dtype == torch.float64 else 1e-3 * cpu.abs().max().item()
    torch.testing.assert_close(gpu.cpu(), cpu, atol=tol, rtol=0)
    est = tc.ContactEstimator(model.to("cuda"))
    c = tc.Contacts(["l_forearm", "l_hand"], ["force", "force"],
                    torch.zeros(1000, 2, 3, dtype=dtype, device="cuda"))  # fmt: skip
    ft = {s: torch.zeros(1000, 6, dtype=dtype, device="cuda") for s in est.sensor_names}
    a = est.estimate(q.cuda(), qd.cuda(), qdd.cuda(), ft, c, backend="cuda")
    b = est.estimate(q.cuda(), qd.cuda(), qdd.cuda(), ft, c, backend="eager")
    torch.testing.assert_close(a.joint_torques, b.joint_torques, atol=tol, rtol=0)
