"""Contact estimator throughput: iDynTree per frame (Python loop) vs ``ContactEstimator`` batched.

Whole iCubGenova04 (icub-models), fixed root_link, all six F/T sensors, a pure force on l_forearm
and one on l_hand, joint torques of all 32 joints, float64 on CPU, the same frames for both.
iDynTree per frame: updateKinematicsFromFixedBase + estimateExtWrenchesAndJointTorques (the root
submodel gets its full-wrench unknown at root_link). torch: ``torch.utils.benchmark`` median.

Run: ``python benchmarks/estimator.py [--profile] [--threads N]``.
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
import time
from pathlib import Path

import torch
import torch.utils.benchmark as tbench

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import idyntree.swig as idt  # noqa: E402
from robots import ROBOTS, load_model, random_state  # noqa: E402

import torchcontact as tc  # noqa: E402

LINKS, KINDS = ["l_forearm", "l_hand"], ["force", "force"]
CHUNK = 20_000  # estimate() does not chunk: bound its working set for the 1e5 run


def make_frames(model, est, n):
    q, qd, qdd = random_state(model, n, seed=0)
    g = torch.Generator().manual_seed(1)
    pos = torch.randn(n, 2, 3, generator=g, dtype=torch.float64) * 0.05
    wr = torch.randn(n, 2, 6, generator=g, dtype=torch.float64) * 10
    wr[..., 3:] = 0
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(LINKS, ["known"] * 2, pos, wrenches=wr))
    return q, qd, qdd, pos, ft


def run_torch(est, q, qd, qdd, pos, ft):
    n = q.shape[0]
    for s in range(0, n, CHUNK):
        e = min(n, s + CHUNK)
        est.estimate(
            q[s:e], qd[s:e], qdd[s:e], {k: v[s:e] for k, v in ft.items()},
            tc.Contacts(LINKS, KINDS, pos[s:e]),
        )  # fmt: skip


def idyntree_setup(model):
    e = idt.ExtWrenchesAndJointTorquesEstimator()
    assert e.loadModelAndSensorsFromFileWithSpecifiedDOFs(
        str(ROBOTS["icub"]()), list(model.joint_names)
    )
    return e


def run_idyntree(e, model, q, qd, qdd, pos, ft, names):
    m, sens = e.model(), e.sensors()
    root = m.getFrameIndex("root_link")
    links = [m.getLinkIndex(lk) for lk in LINKS]
    grav = idt.Vector3.FromPython([0.0, 0.0, -9.81])
    meas = idt.SensorsMeasurements(sens)
    cw, tau = idt.LinkContactWrenches(m), idt.JointDOFsDoubleArray(m)
    u = idt.LinkUnknownWrenchContacts(m)
    T = idt.SIX_AXIS_FORCE_TORQUE
    idx = [sens.getSensorIndex(T, s) for s in names]
    qn, qdn, qddn, pn = q.numpy(), qd.numpy(), qdd.numpy(), pos.numpy()
    ftn = [ft[s].numpy() for s in names]
    for i in range(q.shape[0]):
        e.updateKinematicsFromFixedBase(
            idt.JointPosDoubleArray.FromPython(qn[i]),
            idt.JointDOFsDoubleArray.FromPython(qdn[i]),
            idt.JointDOFsDoubleArray.FromPython(qddn[i]),
            root,
            grav,
        )
        u.clear()
        u.addNewUnknownFullWrenchInFrameOrigin(m, root)
        for k, li in enumerate(links):
            u.addNewContactForLink(
                li, idt.UnknownWrenchContact(idt.PURE_FORCE, idt.Position.FromPython(pn[i, k]))
            )
        for j, r in zip(idx, ftn, strict=True):
            meas.setMeasurement(T, j, idt.Wrench.FromPython(r[i]))
        e.estimateExtWrenchesAndJointTorques(u, meas, cw, tau)


def metadata():
    try:
        commit = subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], text=True).strip()
    except Exception:  # noqa: BLE001
        commit = "?"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (
        f"commit {commit}, torch {torch.__version__}, threads {torch.get_num_threads()},"
        f" CPU {cpu}, python {platform.python_version()}"
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 100, 10_000, 100_000])
    ap.add_argument("--idyntree-frames", type=int, default=2000)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--profile", action="store_true", help="torch.profiler at batch 1e4")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    model = load_model("icub")
    est = tc.ContactEstimator(model)
    names = list(est.sensor_names)
    print(metadata())
    # iDynTree: per-frame cost does not depend on the batch; time it once on the same frames
    nid = args.idyntree_frames
    frames = make_frames(model, est, max(max(args.sizes), nid))
    e = idyntree_setup(model)
    sub = [x[:nid] for x in frames[:4]] + [{k: v[:nid] for k, v in frames[4].items()}]
    run_idyntree(
        e, model, *(x[:10] for x in sub[:4]), {k: v[:10] for k, v in sub[4].items()}, names
    )
    t0 = time.perf_counter()
    run_idyntree(e, model, *sub, names)
    idt_fps = nid / (time.perf_counter() - t0)
    print(f"iDynTree per frame from Python: {idt_fps:,.0f} frames/s ({nid} frames)")
    print(f"{'batch':>8} {'median s':>10} {'IQR s':>10} {'frames/s':>12} {'vs iDynTree':>12}")
    for n in args.sizes:
        q, qd, qdd, pos = (x[:n] for x in frames[:4])
        ft = {k: v[:n] for k, v in frames[4].items()}
        t = tbench.Timer(
            "run_torch(est, q, qd, qdd, pos, ft)",
            globals=dict(run_torch=run_torch, est=est, q=q, qd=qd, qdd=qdd, pos=pos, ft=ft),
        )
        m = t.blocked_autorange(min_run_time=1.0 if n < 100_000 else 3.0)
        fps = n / m.median
        print(f"{n:>8} {m.median:>10.4g} {m.iqr:>10.2g} {fps:>12,.0f} {fps / idt_fps:>11.2f}x")
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        n = 10_000
        q, qd, qdd, pos = (x[:n] for x in frames[:4])
        ft = {k: v[:n] for k, v in frames[4].items()}
        run_torch(est, q, qd, qdd, pos, ft)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(3):
                run_torch(est, q, qd, qdd, pos, ft)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12))


if __name__ == "__main__":
    main()
