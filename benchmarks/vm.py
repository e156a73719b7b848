"""The tape VM against the compiled per-robot kernel and eager torch, in one process.

The program is the estimator a first ``torchcontact estimate`` of ``benchmarks/pipeline.py``'s
log builds (iCub: iCubGenova04, sensor ``l_arm_ft``, 0-2 pure forces on ``l_forearm``/``l_hand``;
or the 7-joint tcarm with ``--robot tcarm``), on that log's first chunk. Each backend runs the
same tensors, one thread (``--threads``), best of ``--repeat`` in thread CPU time, so that a
loaded machine changes the ratios little. Columns: frames/s, the ratio to the compiled kernel,
the largest difference to eager torch (relative to 1 + |value|; NaN patterns must match), and
the one-off cost (the VM's and the kernel's compiler wall seconds, the bytecode's encoding).
The VM is also timed with other blocks (``--blocks``: frames per instruction). Run::

    python benchmarks/vm.py                     # iCub, float64, the table in docs/kernel_cache.md
    python benchmarks/vm.py --robot tcarm --dtype float32 --blocks 32 64 128
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import metadata  # noqa: E402
from kernel_build import capture  # noqa: E402


def best_time(fn, repeat: int) -> float:
    """Least thread CPU seconds of ``repeat`` calls (one thread: the caller's)."""
    best = float("inf")
    for _ in range(repeat):
        t = time.thread_time()
        fn()
        best = min(best, time.thread_time() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", choices=["icub", "tcarm"], default="icub")
    ap.add_argument("--frames", type=int, default=8192, help="frames timed")
    ap.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    ap.add_argument("--blocks", type=int, nargs="*", default=[], help="other VM blocks to time")
    ap.add_argument("--repeat", type=int, default=5, help="timings per backend (best is kept)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-kernel", action="store_true", help="skip the compiled kernel's build")
    args = ap.parse_args()

    import torch

    from torchcontact import kernels
    from torchcontact.kernels import _store, _vm
    from torchcontact.kernels.runner import run_program

    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    tmp = Path(tempfile.mkdtemp(prefix="tc-vm-"))
    os.environ["TORCHCONTACT_CACHE"] = str(tmp / "cache")
    prog, tensors = capture(tmp, args.robot, args.frames)
    tensors = {k: v.to(dtype) for k, v in tensors.items()}
    n = next(iter(tensors.values())).shape[0]
    tr, out = prog.trace()
    t0 = time.perf_counter()
    bc = _vm.encode(tr, out)
    t_encode = time.perf_counter() - t0
    print(metadata())
    print(f"program: estimator of the {args.robot} benchmark log, {len(bc.code):,} instructions,"
          f" {bc.nslots:,} slots ({len(bc.consts)} constants); {n:,} frames {args.dtype};"
          f" load average at start {os.getloadavg()[0]:.1f}")  # fmt: skip
    eager = run_program(prog, tensors, "eager", n)
    rows = []

    def vm_call(block: int):
        dts = kernels._DTYPES[dtype]
        src = _vm.source(dts, kernels._vector_bytes(), block)
        e = _store.Entry(tmp / "cache" / "kernels", f"tck_vm-{dts}_b{block}")
        _vm.write_source(e, src)
        t = time.perf_counter()
        _vm.build(e)
        wall = time.perf_counter() - t
        fn = _vm.load_function(e)
        saved = _vm.BLOCK
        _vm.BLOCK = block  # pieces of threaded calls are whole blocks
        try:
            return _vm.bind(fn, prog, dtype, bc), wall
        finally:
            _vm.BLOCK = saved

    call, wall = vm_call(_vm.BLOCK)
    rows.append((f"VM (block {_vm.BLOCK})", call, f"{wall:.1f} s build, {t_encode:.2f} s encode"))
    for b in args.blocks:
        if b != _vm.BLOCK:
            c, w = vm_call(b)
            rows.append((f"VM (block {b})", c, f"{w:.1f} s build"))
    if not args.no_kernel:
        t = time.perf_counter()
        k = kernels.compiled(prog, dtype, "cpu", wait=True)
        rows.insert(0, ("compiled kernel", k, f"{time.perf_counter() - t:.1f} s build"))
    rows.append(("eager torch", lambda x: run_program(prog, x, "eager", n), ""))

    from kernel_build import rel_diff

    results = []
    for name, fn, note in rows:
        got = fn(tensors)
        fps = n / best_time(lambda fn=fn: fn(tensors), args.repeat)
        results.append((name, fps, rel_diff(got, eager), note))
    ref = {name: fps for name, fps, _, _ in results}
    comp, eag = ref.get("compiled kernel"), ref["eager torch"]
    print()
    print("| backend | frames/s | vs compiled | vs eager | diff vs eager | one-off |")
    print("|---|---:|---:|---:|---:|---|")
    for name, fps, diff, note in results:
        vs = f"{fps / comp:.2f}" if comp else "-"
        print(f"| {name} | {fps:,.0f} | {vs} | {fps / eag:.1f} | {diff:.1e} | {note} |")


if __name__ == "__main__":
    main()
