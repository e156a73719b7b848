"""``torchcontact view``: time and peak memory against the log's length (flat memory).

Simulates one log of the bundled tcarm (the longest size), estimates it, and views its first N
rows for each N, each in a fresh process (``--end`` window; peak RSS from ``getrusage``). Flat
memory: the peak RSS does not grow with N. Reference in the same run: the peak RSS of a process
that only imports torchcontact, torch and rerun (what any view costs before the first frame).

    python benchmarks/view.py [--frames 5000 20000 50000] [--batch-size 2000] [--every 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = r"""
import json, resource, sys, time
import torch
torch.set_num_threads(1)
import rerun
from torchcontact.view import view_log
from torchcontact.robots import tcarm_path
log, est, out, end, batch, every = sys.argv[1:7]
t = time.perf_counter()
s = {"frames": 0}
if end != "none":
    s = view_log(log, est, tcarm_path(), out, end=float(end), batch_size=int(batch),
                 every=int(every))
s["seconds"] = time.perf_counter() - t
s["maxrss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(s))
"""


def _run(*args: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(out.stderr)
    return json.loads(out.stdout.splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, nargs="+", default=[5000, 20000, 50000])
    p.add_argument("--batch-size", type=int, default=2000)
    p.add_argument("--every", type=int, default=1)
    args = p.parse_args()
    import torch

    import torchcontact as tc
    from torchcontact.logs import estimate_file, write_simulated_log

    torch.set_num_threads(1)
    d = Path(tempfile.mkdtemp())
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    n = max(args.frames)
    t = time.perf_counter()
    log = write_simulated_log(model, n, d / "log.parquet", seed=0)
    est = estimate_file(log, model, d / "est.parquet")["output"]
    print(f"# simulated and estimated {n} frames in {time.perf_counter() - t:.1f} s")
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    print(
        f"# commit {commit}, torch {torch.__version__}, {platform.machine()},"
        f" {os.cpu_count()} cores, batch {args.batch_size}, every {args.every}; measured under"
        " whatever load the machine has"
    )
    ref = _run(str(log), str(est), str(d / "x.rrd"), "none", "1", "1")
    print("| frames | seconds | frames/s | peak RSS MB | RSS - imports MB | .rrd MB |")
    print("|---:|---:|---:|---:|---:|---:|")
    print(f"| 0 (imports only) | | | {ref['maxrss_mb']:.0f} | 0 | |")
    for frames in args.frames:
        out = d / f"v{frames}.rrd"
        end = (frames - 0.5) * 0.01  # 100 Hz: the first `frames` rows
        r = _run(str(log), str(est), str(out), f"{end}", str(args.batch_size), str(args.every))
        size = out.stat().st_size / 1e6
        print(
            f"| {r['frames']} | {r['seconds']:.1f} | {r['frames'] / r['seconds']:.0f} |"
            f" {r['maxrss_mb']:.0f} | {r['maxrss_mb'] - ref['maxrss_mb']:.0f} | {size:.1f} |"
        )


if __name__ == "__main__":
    main()
