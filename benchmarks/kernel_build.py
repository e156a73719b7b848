"""Build time of a generated CPU kernel against its speed: one function or parts, one or more units.

The kernel is the estimator of ``benchmarks/pipeline.py``'s iCub log (iCubGenova04, sensor
``l_arm_ft``, 0-2 pure forces on ``l_forearm``/``l_hand``: the kernel a first ``torchcontact
estimate`` of that log builds). For each variant the C++ source is emitted with ``part_nodes``
nodes per function (0: the whole program in one function, as before), compiled by the cache's
builder (:func:`torchcontact.kernels._store.build`, the kernels' flags) into a fresh cache with
``units`` compile slots (the parts compiled as that many translation units at once), then loaded
and timed in this process on the log's first frames (one thread, best of ``--repeat``), and its
outputs compared with the one-function kernel's and eager torch's. Run on a quiet machine::

    python benchmarks/kernel_build.py            # the table in docs/kernel_cache.md
    python benchmarks/kernel_build.py --parts 0 1000 --units 1 4     # quicker
    python benchmarks/kernel_build.py --opt -O1  # another optimisation level

Columns: the source's size and part functions, the build's wall seconds and the compilers' CPU
seconds (children's user + system), the kernel's frames/s, their ratios to the first variant
(the one-function kernel), the largest difference to the first variant's outputs and to eager
torch (relative to 1 + |value|; NaN patterns must match).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import metadata  # noqa: E402


def capture(tmp: Path, robot: str = "icub", frames: int = 8192):
    """The estimator program of the benchmark log and the tensors of its first chunk."""
    import pipeline as bp

    import torchcontact as tc
    from torchcontact.estimation import estimator as est_mod
    from torchcontact.logs import estimate_file

    log = bp.write_log(robot, frames, tmp / f"{robot}{frames}.parquet")
    seen = []
    run = est_mod.run_program

    def spy(prog, tensors, backend, chunk_size):
        if prog.name == "estimator" and not seen:
            seen.append((prog, {k: v.clone() for k, v in tensors.items()}))
        return run(prog, tensors, "eager", chunk_size)

    est_mod.run_program = spy
    try:
        urdf, _, _ = bp.robot_setup(robot)
        model = tc.RobotModel.from_urdf(urdf)
        estimate_file(log, model, tmp / "out.parquet", batch_size=frames, progress=False)
    finally:
        est_mod.run_program = run
    return seen[0]


def rel_diff(a: dict, b: dict) -> float:
    """Largest ``|a - b| / (1 + |b|)`` over the outputs; inf where the NaN patterns differ."""
    worst = 0.0
    for k in b:
        if not bool((a[k].isnan() == b[k].isnan()).all()):
            return float("inf")
        d = ((a[k] - b[k]).abs() / (1 + b[k].abs())).nan_to_num(0.0)
        worst = max(worst, float(d.max()) if d.numel() else 0.0)
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", type=int, nargs="+", default=[0, 500, 1000, 2000],
                    help="nodes per function (0: one function)")  # fmt: skip
    ap.add_argument(
        "--units",
        type=int,
        nargs="+",
        default=[1, 2, 4],
        help="compile slots (translation units at once) for a source in parts",
    )
    ap.add_argument("--opt", default="-O2", help="optimisation flag instead of -O2")
    ap.add_argument("--repeat", type=int, default=20, help="kernel timings (best is kept)")
    args = ap.parse_args()

    import ctypes

    import torch

    from torchcontact import kernels
    from torchcontact.kernels import _cpp, _store
    from torchcontact.kernels.runner import run_program

    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="tc-kernel-build-"))
    os.environ["TORCHCONTACT_CACHE"] = str(tmp / "cache")
    prog, tensors = capture(tmp)
    tr, out = prog.trace()
    n = next(iter(tensors.values())).shape[0]
    eager = run_program(prog, tensors, "eager", n)
    flags = tuple(args.opt if f == "-O2" else f for f in _store.CFLAGS)
    variants = [(p, 1) for p in args.parts if p == 0]
    variants += [(p, u) for p in args.parts if p for u in args.units]
    print(metadata())
    print(f"kernel: estimator of the iCub benchmark log, {len(_cpp.live_nodes(tr, [x for xs in out.values() for x in xs])):,} nodes;"  # noqa: E501
          f" {n:,} frames; flags {' '.join(flags)}; {_store.cores()} cores;"
          f" load average at start {os.getloadavg()[0]:.1f}")  # fmt: skip
    print()
    print(
        "| nodes per function | functions | source (kB) | units | build (s) | compiler CPU (s) "
        "| kernel (frames/s) | build vs first | kernel vs first | diff vs first | diff vs eager |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    first = None
    for i, (part_nodes, units) in enumerate(variants):
        src = _cpp.emit(tr, out, "double", vbytes=kernels._vector_bytes(), part_nodes=part_nodes)
        entry = _store.Entry(tmp / f"cache{i}" / "kernels", f"tck_estimator_v{i}")
        entry.dir.mkdir(parents=True)
        _store.write_atomic(entry.source, src)
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        _store.build(entry, jobs=units, flags=flags)
        wall = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime
        fn = kernels._wrap(ctypes.CDLL(str(entry.library)).tc_kernel, prog, torch.float64)
        got = fn(tensors)
        best = float("inf")
        for _ in range(args.repeat):
            t = time.thread_time()
            fn(tensors)
            best = min(best, time.thread_time() - t)
        fps = n / best
        if first is None:
            first = (wall, fps, got)
        units_used = (entry.record() or {}).get("units", 1)
        parts = _store.source_parts(entry.source)
        print(f"| {part_nodes or 'all'} | {parts} | {len(src) / 1e3:.0f}"
              f" | {units_used} | {wall:.2f} | {cpu:.2f} | {fps:,.0f} | {wall / first[0]:.2f}"
              f" | {fps / first[1]:.2f} | {rel_diff(got, first[2]):.1e}"
              f" | {rel_diff(got, eager):.1e} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
