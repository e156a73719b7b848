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
   empty cache: when the output is published, when the command exits, how many compilers ran at
   once (sampled from ``/proc`` every 50 ms) and whether builds went on after the exit.

Run alone on a quiet machine: ``python benchmarks/kernel_cache.py [--repeat 7]`` and
``python benchmarks/kernel_cache.py --first-run [--frames 20000]``; for the code before this
cache, the same with ``PYTHONPATH`` at a checkout of that commit (``git archive 4b41f9f``).
"""

from __future__ import annotations

import argparse
import os
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


def _compilers() -> int:
    n = 0
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                n += (d / "comm").read_text().strip() in ("cc1plus", "cc1")
            except OSError:
                pass
    return n


def first_run(frames: int, batch: int) -> None:
    import icub_models

    work = Path(tempfile.mkdtemp(prefix="tc-first-"))
    env = {**os.environ, "TORCHCONTACT_CACHE": str(work / "cache")}
    urdf = icub_models.get_model_file("iCubGenova04")
    log, out = work / "icub.parquet", work / "out.parquet"
    subprocess.run([sys.executable, "-m", "torchcontact.cli", "simulate", "--robot", urdf,
                    "--sensor", "l_arm_ft", "--frames", str(frames), "--seed", "2", "--quiet",
                    "--out", str(log)], env=env, check=True, capture_output=True)  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "torchcontact.cli", "estimate", str(log),
                             "--robot", urdf, "--sensor", "l_arm_ft", "--batch-size", str(batch),
                             "--quiet", "--out", str(out)], env=env, stderr=subprocess.PIPE,
                            text=True)  # fmt: skip
    published, most = None, 0
    while proc.poll() is None:
        most = max(most, _compilers())
        if published is None and out.exists():
            published = time.perf_counter() - t0
        time.sleep(0.05)
    exited = time.perf_counter() - t0
    after = 0.0
    while _compilers():  # builds that outlive the command
        most = max(most, _compilers())
        time.sleep(0.05)
        after += 0.05
    notes = [ln for ln in proc.stderr.read().splitlines() if ln.startswith("note:")]
    builds = len(list((work / "cache" / "kernels").glob("tck_*/entry.json")))
    print(f"\nfirst run, {frames} simulated iCub frames, --batch-size {batch}, empty cache")
    print("| output published (s) | exited (s) | exit after publishing (s) | compilers at once |"
          " kernels built | compiling after the exit (s) |")  # fmt: skip
    print("|---:|---:|---:|---:|---:|---:|")
    print(
        f"| {published or float('nan'):.1f} | {exited:.1f} |"
        f" {exited - (published or exited):.1f} | {most} | {builds} | {after:.1f} |"
    )
    print("stderr note:", notes[0] if notes else "(none)")


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
