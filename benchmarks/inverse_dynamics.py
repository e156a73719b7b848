"""Inverse dynamics throughput: pinocchio's ``pin.rnea`` per frame vs torchcontact's backends.

Same frames for all, float64 (and float32 for torchcontact), batch 1e5 by default. ``pin.rnea``
is called from a Python loop, in one process and in one process per core (the CPU's total). The
torchcontact backends: ``eager`` (the physics program on torch tensors), ``cpu`` (the generated
C++ kernel, frames split over ``torch.get_num_threads()`` threads) and ``cuda`` when a GPU is
present. "first result" is the wall time of a new process from its first line to its first torque
vector: cold (empty kernel cache: the kernel is built) and warm (the disk cache is loaded).

Run alone on a quiet machine: ``python benchmarks/inverse_dynamics.py [--robots panda icub]
[--batch 100000] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _meta import first_call, metadata, rate  # noqa: E402
from robots import ROBOTS, PinRobot  # noqa: E402

import torchcontact as tc  # noqa: E402


def _pin_worker(args) -> float:
    """Frames/s of ``pin.rnea`` in a Python loop over ``n`` frames (one process)."""
    name, seed, n = args
    import pinocchio as pin

    path = ROBOTS[name]()
    ref = PinRobot(path, tc.RobotModel.from_urdf(path))
    rng = np.random.default_rng(seed)
    nv = len(ref.Q)
    qs, vs, acs = ([f(x) for x in rng.uniform(-1, 1, (n, nv))] for f in (ref.q, ref.v, ref.v))
    t = time.perf_counter()
    for a, b, c in zip(qs, vs, acs, strict=True):
        pin.rnea(ref.m, ref.d, a, b, c)
    return n / (time.perf_counter() - t)


def pin_rates(name: str, n: int = 30_000) -> tuple[float, float]:
    """``pin.rnea`` frames/s in one process and summed over one process per CPU."""
    one = _pin_worker((name, 0, n))
    cores = os.cpu_count() or 1
    with mp.get_context("spawn").Pool(cores) as pool:
        many = sum(pool.map(_pin_worker, [(name, i, n) for i in range(cores)]))
    return one, many


FIRST = """
import time; t = time.perf_counter()
import sys; sys.path.insert(0, "tests")
import torch, torchcontact as tc
from robots import ROBOTS, random_state
torch.set_num_threads({threads})
m = tc.RobotModel.from_urdf(ROBOTS["{name}"]())
q, qd, qdd = random_state(m, 100_000, seed=0)
m.inverse_dynamics(q, qd, qdd, backend="cpu")
print(time.perf_counter() - t)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=["panda", "icub"])
    ap.add_argument("--batch", type=int, default=100_000)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--no-first", action="store_true", help="skip the first-result timings")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(metadata())
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    n = args.batch
    for name in args.robots:
        base = tc.RobotModel.from_urdf(ROBOTS[name]())
        one, many = pin_rates(name)
        print(f"\n{name}: nv={base.nv}, bodies={base.nb}, batch {n:,}")
        print(f"  pin.rnea loop: {one:,.0f} frames/s in 1 process, {many:,.0f} on all cores")
        rng = np.random.default_rng(0)
        q, qd, qdd = (rng.uniform(-1, 1, (n, base.nv)) for _ in range(3))
        head = ("device", "dtype", "backend", "frames/s", "IQR", "x pin 1 proc", "x pin cores")
        print("  {:6} {:8} {:7} {:>13} {:>6} {:>13} {:>12}".format(*head))
        for device in devices:
            for dtype in (torch.float64, torch.float32):
                model = base.to(device=device, dtype=dtype)
                T = [torch.as_tensor(x, dtype=dtype, device=device) for x in (q, qd, qdd)]
                sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
                backends = ["eager", "cpu" if device == "cpu" else "cuda"]
                for be in backends:
                    model.inverse_dynamics(*T, backend=be)  # build / warm up

                    def run(m=model, be=be, T=T, sync=sync):
                        m.inverse_dynamics(*T, backend=be)
                        sync()

                    fps, iqr = rate(run, n)
                    print(f"  {device:6} {str(dtype)[6:]:8} {be:7} {fps:>13,.0f} {iqr:>6.0%}"
                          f" {fps / one:>13.1f} {fps / many:>12.1f}")  # fmt: skip
        if not args.no_first:
            code = FIRST.format(name=name, threads=args.threads)
            cache = tempfile.mkdtemp(prefix="tc-cache-")
            cold = first_call(code, cache)
            warm = first_call(code, cache)
            print(f"  first result of a new process (cpu, float64, 1e5 frames): cold {cold:.1f} s"
                  f" (kernel built), warm {warm:.1f} s (disk cache)")  # fmt: skip


if __name__ == "__main__":
    main()
