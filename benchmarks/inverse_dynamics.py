"""Frames/s of batched inverse dynamics vs pinocchio's ``pin.rnea`` looped over the same frames.

Usage: ``python benchmarks/inverse_dynamics.py [--robots panda icub] [--max-batch 1000000]``.
Prints a table per robot: torch eager and compiled (``tc.compiled_inverse_dynamics``) in float64
and float32 on CPU (and CUDA when present), the pin.rnea loop, and the ratios; plus the time to
first result of the compiled path (compile included). Timings: ``torch.utils.benchmark`` medians.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.utils.benchmark as tb

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _meta import metadata  # noqa: E402
from robots import ROBOTS, PinRobot  # noqa: E402

import torchcontact as tc  # noqa: E402


def median_time(fn, min_run_time=1.0) -> float:
    return (
        tb.Timer(stmt="fn()", globals={"fn": fn})
        .blocked_autorange(min_run_time=min_run_time)
        .median
    )


def pin_loop_rate(ref: PinRobot, q, qd, qdd, n=20000) -> float:
    import pinocchio as pin

    n = min(n, len(q))
    qs = [ref.q(x) for x in q[:n]]
    vs = [ref.v(x) for x in qd[:n]]
    acs = [ref.v(x) for x in qdd[:n]]
    t = time.perf_counter()
    for a, b, c in zip(qs, vs, acs, strict=True):
        pin.rnea(ref.m, ref.d, a, b, c)
    return n / (time.perf_counter() - t)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=["panda", "icub"])
    ap.add_argument("--max-batch", type=int, default=1_000_000)
    ap.add_argument("--no-compile", action="store_true")
    args = ap.parse_args()
    print(metadata())
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    batches = [b for b in (1, 100, 10_000, 100_000, 1_000_000) if b <= args.max_batch]
    for name in args.robots:
        path = ROBOTS[name]()
        base = tc.RobotModel.from_urdf(path)
        ref = PinRobot(path, base)
        rng = np.random.default_rng(0)
        nmax = max(batches)
        q, qd, qdd = (rng.uniform(-1, 1, (nmax, base.nv)) for _ in range(3))
        pin_rate = pin_loop_rate(ref, q, qd, qdd)
        print(f"\n{name}: nv={base.nv}, bodies={base.nb}; pin.rnea loop: {pin_rate:,.0f} frames/s")
        head = ("device", "dtype", "batch", "eager f/s", "compiled f/s", "x pin loop")
        print("{:6} {:8} {:>9} {:>13} {:>13} {:>10}".format(*head))
        for device in devices:
            for dtype in (torch.float64, torch.float32):
                model = base.to(device=device, dtype=dtype)
                T = [torch.as_tensor(x, dtype=dtype, device=device) for x in (q, qd, qdd)]
                compiled = None
                if not args.no_compile:
                    compiled = tc.compiled_inverse_dynamics(model, chunk_size=4096)
                    t0 = time.perf_counter()
                    compiled(*(x[:1] for x in T))
                    first = time.perf_counter() - t0
                    print(f"  compiled first result ({device}, {dtype}): {first:.1f} s")
                for b in batches:
                    args_b = [x[:b] for x in T]
                    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)

                    def timed(fn, args_b=args_b, sync=sync, b=b):
                        return b / median_time(lambda: (fn(*args_b), sync()))

                    e_rate = timed(model.inverse_dynamics)
                    c_rate = float("nan") if compiled is None else timed(compiled)
                    best = max(e_rate, c_rate if c_rate == c_rate else 0)
                    print(
                        f"{device:6} {str(dtype)[6:]:8} {b:>9,} {e_rate:>13,.0f} {c_rate:>13,.0f}"
                        f" {best / pin_rate:>10.2f}"
                    )


if __name__ == "__main__":
    main()
