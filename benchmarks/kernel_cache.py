"""Kernel cache: the cost of a cache hit in a fresh process, and a first run's builds.

1. **Cache hit** (default). The whole-iCub estimator (iCubGenova04, all six F/T sensors, a pure
   force on l_forearm and one on l_hand, float64), its kernel built once into a temporary cache.
   Then fresh processes, each timing one way to get the kernel from the disk cache (after the
   imports and the model, which both pay):

   - *retrace* (before, the reference): trace the program, emit its C++, hash it, load the
     library: what every process did before the index (``kernels._source`` + load);
   - *index*: ``kernels.compiled(..., wait=False)``: the key's index record, the library's
     size and sha256 checked against its entry's record, load.

2. **First run** (``--first-run``): ``torchcontact estimate`` on a simulated iCub log with an
   empty cache, then again with the cache it filled: when the output is published, when the
   command exits, how many compilers and build processes ran at once (sampled from ``/proc``
   every 50 ms), how long builds went on after the exit. The second run's exit delay is the
   interpreter's own shutdown, without builds.

Run alone on a quiet machine: ``python benchmarks/kernel_cache.py [--repeat 7]`` and
``python benchmarks/kernel_cache.py --first-run [--frames 20000]``; for the code before this
cache, the same with ``PYTHONPATH`` at a checkout of that commit (``git archive 4b41f9f``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import ROOT, metadata  # noqa: E402

SETUP = """
import sys, time, torch, icub_models, torchcontact as tc
from torchcontact import kernels
from torchcontact.estimation import programs
m = tc.RobotModel.from_urdf(icub_models.get_model_file("iCubGenova04"))
est = tc.ContactEstimator(m)
em = est.layout(["l_forearm", "l_hand"], ["force", "force"])
prog = programs.program(em, "estimate", False, False, False)
"""

WAYS = {
    "retrace (before)": """
t = time.perf_counter()
src, h = kernels._source(prog, torch.float64)
name, cpp, so = kernels._paths(prog, h)
k = kernels._wrap(__import__("ctypes").CDLL(str(so)).tc_kernel, prog, torch.float64)
print(time.perf_counter() - t)
""",
    "index (now)": """
t = time.perf_counter()
k = kernels.compiled(prog, torch.float64, wait=False)
assert k is not None and not prog._traced
print(time.perf_counter() - t)
""",
}


def fresh(code: str, cache: str) -> float:
    env = {**os.environ, "TORCHCONTACT_CACHE": cache}
    out = subprocess.run([sys.executable, "-c", SETUP + code], env=env, cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout  # fmt: skip
    return float(out.strip().splitlines()[-1])


def cache_hit(repeat: int) -> None:
    cache = tempfile.mkdtemp(prefix="tc-cache-")
    t = time.perf_counter()
    fresh("kernels.compiled(prog, torch.float64)\nprint(0)", cache)  # build it, index it
    print(f"kernel built in {time.perf_counter() - t:.1f} s (one process, imports included)")
    times: dict[str, list[float]] = {w: [] for w in WAYS}
    for _ in range(repeat):  # interleaved: the machine's load affects both alike
        for way, code in WAYS.items():
            times[way].append(fresh(code, cache))
    ref = statistics.median(times["retrace (before)"])
    print(f"\ncache hit in a fresh process, {repeat} processes each (median, min-max)")
    print("| way | median (ms) | min-max (ms) | vs retrace |")
    print("|---|---:|---:|---:|")
    for way, ts in times.items():
        med = statistics.median(ts)
        vs = "1" if way == "retrace (before)" else f"{ref / med:.1f}x faster"
        print(f"| {way} | {1e3 * med:.1f} | {1e3 * min(ts):.1f}-{1e3 * max(ts):.1f} | {vs} |")


def _processes(work: Path) -> tuple[int, int]:
    """``(compilers, kernel builders)`` of this run running now (Linux ``/proc``).

    Only processes whose current folder is under ``work`` count: other users' compilers on the
    machine do not.
    """
    compilers = builders = 0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if not os.readlink(d / "cwd").startswith(str(work)):
                continue
            comm = (d / "comm").read_text().strip()
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        compilers += comm in ("cc1plus", "cc1")
        builders += b"_store.py build" in cmd or b"-m torchcontact.kernels" in cmd
    return compilers, builders


def _estimate(work: Path, env: dict, args: list[str], out: Path) -> dict:
    """One ``torchcontact estimate``: publish and exit times, processes at once, builds after."""
    out.unlink(missing_ok=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "torchcontact.cli", "estimate", *args,
                             "--quiet", "--out", str(out)], env=env, stderr=subprocess.PIPE,
                            text=True, cwd=work)  # fmt: skip
    published, most, most_builders = None, 0, 0
    while proc.poll() is None:
        c, b = _processes(work)
        most, most_builders = max(most, c), max(most_builders, b)
        if published is None and out.exists():
            published = time.perf_counter() - t0
        time.sleep(0.05)
    exited = time.perf_counter() - t0
    while any(_processes(work)):  # builds that outlive the command
        c, b = _processes(work)
        most, most_builders = max(most, c), max(most_builders, b)
        time.sleep(0.05)
    notes = [ln for ln in proc.stderr.read().splitlines() if ln.startswith("note:")]
    return {"published": published or float("nan"), "exited": exited, "compilers": most,
            "builders": most_builders, "after": time.perf_counter() - t0 - exited,
            "note": notes[0] if notes else "(none)"}  # fmt: skip


def first_run(frames: int, batch: int) -> None:
    import icub_models

    work = Path(tempfile.mkdtemp(prefix="tc-first-"))
    env = {**os.environ, "TORCHCONTACT_CACHE": str(work / "cache")}
    urdf = icub_models.get_model_file("iCubGenova04")
    log = work / "icub.parquet"
    subprocess.run([sys.executable, "-m", "torchcontact.cli", "simulate", "--robot", urdf,
                    "--sensor", "l_arm_ft", "--frames", str(frames), "--seed", "2", "--quiet",
                    "--out", str(log)], env=env, check=True, capture_output=True,
                   cwd=work)  # fmt: skip
    shutil.rmtree(work / "cache", ignore_errors=True)  # the simulator's kernels: a cold start
    args = [str(log), "--robot", urdf, "--sensor", "l_arm_ft", "--batch-size", str(batch)]
    rows = {"first (empty cache)": _estimate(work, env, args, work / "first.parquet")}
    builds = len(list((work / "cache" / "kernels").glob("tck_*/*.so")))
    rows["second (warm cache)"] = _estimate(work, env, args, work / "second.parquet")
    print(f"\n{frames} simulated iCub frames, --batch-size {batch}; {builds} kernels built")
    print(
        "| run | output published (s) | exited (s) | exit after publishing (s) |"
        " compilers at once | build processes at once | building after the exit (s) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, r in rows.items():
        print(
            f"| {name} | {r['published']:.1f} | {r['exited']:.1f} |"
            f" {r['exited'] - r['published']:.1f} | {r['compilers']} | {r['builders']} |"
            f" {r['after']:.1f} |"
        )
    print("first run's stderr note:", rows["first (empty cache)"]["note"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7, help="fresh processes per way")
    ap.add_argument("--first-run", action="store_true", help="time a cold estimate instead")
    ap.add_argument("--frames", type=int, default=20000, help="frames of the first-run log")
    ap.add_argument("--batch", type=int, default=2048, help="--batch-size of the first run")
    args = ap.parse_args()
    print(metadata())
    if args.first_run:
        first_run(args.frames, args.batch)
    else:
        cache_hit(args.repeat)


if __name__ == "__main__":
    main()
