"""Contact estimator throughput: iDynTree's estimator per frame vs torchcontact's backends.

Whole iCubGenova04 (icub-models), fixed root_link, all six F/T sensors (six regions), a pure force
on l_forearm and one on l_hand (rank 5 of 6: the paper's case), joint torques of all 32 joints,
the same frames for every method. iDynTree per frame: updateKinematicsFromFixedBase +
estimateExtWrenchesAndJointTorques from a Python loop (its root submodel gets a full-wrench
unknown at root_link), in one process and in one process per CPU. torchcontact: ``eager`` and the
generated ``cpu`` kernel (threads: ``--threads``), float64 and float32; "first result" is a new
process's wall time to its first estimate, with an empty kernel cache (cold: ``backend="auto"``
estimates eagerly while the kernel builds) and with the disk cache (warm).

Run alone on a quiet machine: ``python benchmarks/estimator.py [--batch 100000] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import idyntree.swig as idt  # noqa: E402
from _meta import first_call, metadata, rate  # noqa: E402
from robots import ROBOTS, load_model, random_state  # noqa: E402

import torchcontact as tc  # noqa: E402

LINKS, KINDS = ["l_forearm", "l_hand"], ["force", "force"]


def make_frames(model, est, n, seed=0):
    q, qd, qdd = random_state(model, n, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    pos = torch.randn(n, 2, 3, generator=g, dtype=torch.float64) * 0.05
    wr = torch.randn(n, 2, 6, generator=g, dtype=torch.float64) * 10
    wr[..., 3:] = 0
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(LINKS, ["known"] * 2, pos, wrenches=wr))
    return q, qd, qdd, pos, ft


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


def _idyntree_worker(args) -> float:
    """Frames/s of iDynTree's estimator over ``n`` frames in one process."""
    seed, n = args
    model = load_model("icub")
    est = tc.ContactEstimator(model)
    frames = make_frames(model, est, n + 10, seed)
    e = idyntree_setup(model)
    warm = [x[:10] for x in frames[:4]] + [{k: v[:10] for k, v in frames[4].items()}]
    run_idyntree(e, model, *warm, est.sensor_names)
    rest = [x[10:] for x in frames[:4]] + [{k: v[10:] for k, v in frames[4].items()}]
    t = time.perf_counter()
    run_idyntree(e, model, *rest, est.sensor_names)
    return n / (time.perf_counter() - t)


FIRST = """
import time; t = time.perf_counter()
import sys; sys.path.insert(0, "tests")
import torch, torchcontact as tc
from robots import ROBOTS, random_state
torch.set_num_threads({threads})
m = tc.RobotModel.from_urdf(ROBOTS["icub"]())
est = tc.ContactEstimator(m)
q, qd, qdd = random_state(m, {n}, seed=0)
ft = {{s: torch.zeros({n}, 6, dtype=torch.float64) for s in est.sensor_names}}
pos = torch.zeros({n}, 2, 3, dtype=torch.float64)
c = tc.Contacts(["l_forearm", "l_hand"], ["force", "force"], pos)
r = est.estimate(q, qd, qdd, ft, c)
print(time.perf_counter() - t)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=100_000)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--idyntree-frames", type=int, default=3000)
    ap.add_argument("--no-first", action="store_true", help="skip the first-result timings")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(metadata())
    n = args.batch
    one = _idyntree_worker((0, args.idyntree_frames))
    cores = os.cpu_count() or 1
    with mp.get_context("spawn").Pool(cores) as pool:
        many = sum(pool.map(_idyntree_worker, [(i, args.idyntree_frames) for i in range(cores)]))
    print(f"iDynTree estimator per frame: {one:,.0f} frames/s in 1 process, {many:,.0f} on all"
          f" cores")  # fmt: skip
    print(f"batch {n:,}, layout {list(zip(LINKS, KINDS, strict=True))}")
    head = ("dtype", "backend", "frames/s", "IQR", "x iDynTree 1 proc", "x iDynTree cores")
    print("{:8} {:7} {:>12} {:>6} {:>18} {:>17}".format(*head))
    for dtype in (torch.float64, torch.float32):
        model = load_model("icub", dtype)
        est = tc.ContactEstimator(model)
        q, qd, qdd, pos, ft = make_frames(load_model("icub"), est if dtype == torch.float64 else
                                          tc.ContactEstimator(load_model("icub")), n)  # fmt: skip
        q, qd, qdd, pos = (x.to(dtype) for x in (q, qd, qdd, pos))
        ft = {k: v.to(dtype) for k, v in ft.items()}
        c = tc.Contacts(LINKS, KINDS, pos)
        for be in ("eager", "cpu"):
            if be == "eager" and n > 20_000:
                m = 20_000  # eager is slow: time a slice
                args_e = (q[:m], qd[:m], qdd[:m], {k: v[:m] for k, v in ft.items()},
                          tc.Contacts(LINKS, KINDS, pos[:m]))  # fmt: skip
            else:
                m, args_e = n, (q, qd, qdd, ft, c)
            est.estimate(*args_e, backend=be)  # build / warm up
            fps, iqr = rate(lambda est=est, a=args_e, be=be: est.estimate(*a, backend=be), m)
            print(f"{str(dtype)[6:]:8} {be:7} {fps:>12,.0f} {iqr:>6.0%} {fps / one:>18.1f}"
                  f" {fps / many:>17.1f}")  # fmt: skip
    if not args.no_first:
        code = FIRST.format(threads=args.threads, n=10_000)
        cache = tempfile.mkdtemp(prefix="tc-cache-")
        cold = first_call(code, cache)
        warm = first_call(code, cache)
        print(f"first estimates of a new process (10,000 frames): cold {cold:.1f} s (eager while"
              f" the kernel builds), warm {warm:.1f} s (disk cache)")  # fmt: skip


if __name__ == "__main__":
    main()
