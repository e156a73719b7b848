"""GPU throughput and many-core CPU scaling of the generated kernels, in one process.

iCubGenova04 (icub-models; fixed root_link) and the bundled tcarm: inverse dynamics (RNEA) and
the whole-body contact estimator (iCub: all six F/T sensors, a pure force on ``l_forearm`` and one
on ``l_hand``, the paper's rank-5 case; tcarm: its base sensor, two pure forces). For each batch
size: the generated ``cuda`` kernel on data already on the GPU (float64 and float32), the same
including the host-to-device copy of the inputs and the copy of the result back, and the
generated ``cpu`` kernel at 1, 2, 4, ... threads up to the machine's cores (the CPU reference,
same frames, same process). Also the wall time of each CUDA kernel's first build (nvcc), and a
float64 check of every CUDA result against the CPU kernel.

Needs only torch, numpy, icub-models and this repository (no pinocchio, no iDynTree).
Run: ``python benchmarks/gpu.py [--batch 10000 100000 1000000] [--robots icub tcarm]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _meta import metadata, rate  # noqa: E402

import torchcontact as tc  # noqa: E402

CASES = {"icub": ["l_forearm", "l_hand"], "tcarm": ["forearm", "hand"]}


def load(name: str) -> tc.RobotModel:
    if name == "icub":
        import icub_models

        return tc.RobotModel.from_urdf(icub_models.get_model_file("iCubGenova04"))
    from torchcontact.robots import tcarm_path

    return tc.RobotModel.from_urdf(tcarm_path())


def frames(model: tc.RobotModel, n: int, links: list[str], seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    q, qd, qdd = (
        (torch.rand(n, model.nv, generator=g, dtype=torch.float64) * 2 - 1) * s
        for s in (1.5, 2.0, 3.0)
    )
    pos = torch.randn(n, len(links), 3, generator=g, dtype=torch.float64) * 0.05
    return q, qd, qdd, pos


def thread_counts() -> list[int]:
    cores, out, t = os.cpu_count() or 1, [], 1
    while t < cores:
        out.append(t)
        t *= 2
    return out + [cores]


def make_job(model, job, links, q, qd, qdd, pos, ft, backend, est=None):
    """A callable running ``job`` ("rnea" or "estimate") on these inputs with ``backend``."""
    est = est or tc.ContactEstimator(model)
    sync = torch.cuda.synchronize if backend == "cuda" else (lambda: None)

    def run():
        if job == "rnea":
            r = model.inverse_dynamics(q, qd, qdd, backend=backend)
        else:
            c = tc.Contacts(links, ["force"] * len(links), pos)
            r = est.estimate(q, qd, qdd, ft, c, backend=backend).joint_torques
        sync()
        return r

    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=["icub", "tcarm"])
    ap.add_argument("--batch", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--min-time", type=float, default=0.5, help="seconds per timing (median)")
    ap.add_argument("--cpu-only", action="store_true", help="skip the CUDA rows")
    args = ap.parse_args()
    print(metadata())
    cuda = torch.cuda.is_available() and not args.cpu_only
    if not cuda:
        print("no CUDA device: CPU rows only")
    head = ("robot", "job", "batch", "device", "dtype", "threads", "frames/s", "IQR", "x cpu 1t")
    fmt = "{:6} {:9} {:>9} {:6} {:8} {:>7} {:>14} {:>5} {:>9}"
    for name in args.robots:
        base = load(name)
        links = CASES[name]
        k = len(links)
        print(f"\n{name}: nv={base.nv}, bodies={base.nb}, contacts {links} (pure forces)")
        print(fmt.format(*head))
        for n in args.batch:
            q, qd, qdd, pos = frames(base, n, links)
            g = torch.Generator().manual_seed(1)
            wr = torch.cat([torch.randn(n, k, 3, generator=g, dtype=torch.float64) * 10,
                            torch.zeros(n, k, 3, dtype=torch.float64)], -1)  # fmt: skip
            known = tc.Contacts(links, ["known"] * k, pos, wrenches=wr)
            ft = tc.ContactEstimator(base).predict_ft(q, qd, qdd, known)
            for job in ("rnea", "estimate"):
                run = make_job(base, job, links, q, qd, qdd, pos, ft, "cpu")
                ref = run()
                one = None
                for threads in thread_counts():
                    torch.set_num_threads(threads)
                    fps, iqr = rate(run, n, args.min_time)
                    one = one or fps
                    row = (name, job, f"{n:,}", "cpu", "float64", threads, f"{fps:,.0f}")
                    print(fmt.format(*row, f"{iqr:.0%}", f"{fps / one:.1f}"))
                torch.set_num_threads(os.cpu_count() or 1)
                if not cuda:
                    continue
                f32 = [t.float() for t in (q, qd, qdd, pos)]
                f32_ft = {s: v.float() for s, v in ft.items()}
                ref32 = make_job(base.to(dtype=torch.float32), job, links, *f32, f32_ft, "cpu")()
                for dtype in (torch.float64, torch.float32):
                    m = base.to(device="cuda", dtype=dtype)
                    # pinned host buffers: the copy rows measure the link, not pageable memcpy
                    host = [x.to(dtype).pin_memory() for x in (q, qd, qdd, pos)]
                    hft = {s: v.to(dtype).pin_memory() for s, v in ft.items()}
                    dev = [x.cuda() for x in host]
                    dft = {s: v.cuda() for s, v in hft.items()}
                    est = tc.ContactEstimator(m)  # built once: not part of any timing
                    run_dev = make_job(m, job, links, *dev, dft, "cuda", est)

                    def run_copy(m=m, job=job, host=host, hft=hft, links=links, est=est):
                        d = [x.cuda(non_blocking=True) for x in host]
                        f = {s: v.cuda(non_blocking=True) for s, v in hft.items()}
                        return make_job(m, job, links, *d, f, "cuda", est)().cpu()

                    t0 = time.perf_counter()
                    out = run_dev()
                    build = time.perf_counter() - t0
                    if n == args.batch[0]:
                        print(f"  (first cuda {job} {str(dtype)[6:]} call, nvcc build or cache"
                              f" load included: {build:.1f} s)")  # fmt: skip
                    # against the CPU kernel in the same dtype (float32 against float64 differs
                    # where float32 finds a lower rank: a property of the precision, not of CUDA)
                    cref = ref if dtype == torch.float64 else ref32
                    err = (out.double().cpu() - cref.double()).abs().max().item()
                    tol = 1e-9 if dtype == torch.float64 else 1e-3 * ref.abs().max().item()
                    fps, iqr = rate(run_dev, n, args.min_time)
                    fpc, _ = rate(run_copy, n, args.min_time)
                    row = (name, job, f"{n:,}", "cuda", str(dtype)[6:], "-", f"{fps:,.0f}")
                    print(fmt.format(*row, f"{iqr:.0%}", f"{fps / one:.0f}")
                          + f"  with copies {fpc:,.0f}/s; max|cuda-cpu, same dtype| {err:.1e}"
                          + ("" if err <= tol else "  MISMATCH"))  # fmt: skip


if __name__ == "__main__":
    main()
