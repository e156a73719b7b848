"""``estimate --track-bias`` on simulated logs with a drifting F/T offset: accuracy, time, memory.

1. **Accuracy**: a simulated tcarm log (100 Hz, one or two force contacts on the skin, half the
   frames in contact) whose ``base_ft`` reading has a constant offset plus a thermal drift
   (``UnmodeledEffects``: ~3 N on the forces within the log) and white noise, estimated
   without tracking, with ``--track-bias`` (forward-backward smoother), with
   ``--track-bias --no-smoother`` (the causal filter, what the robot tracks online), and the
   same trajectory without offset and drift (the oracle). Contact-force RMSE against the
   simulated truth on the ok frames with one contact (well posed) and with two.
2. **Time and memory**: the CLI (``torchcontact estimate``) in a child process per run, with and
   without ``--track-bias``, on two log lengths; wall time and peak RSS (``ru_maxrss`` of the
   child). The bias pass keeps one chunk in memory and writes 64 bytes per frame and sensor to
   ``OUT.partial/bias.states``: the peak RSS must not grow with the log.

Run: ``python benchmarks/track_bias.py [--frames 20000] [--long 200000]`` (the numbers of
docs/online.md were taken on a shared 2-core machine: compare within a table).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import torch

import torchcontact as tc
from torchcontact.logs import estimate_file, write_simulated_log
from torchcontact.logs.chunks import LogBias
from torchcontact.simulation import UnmodeledEffects

NOISE = (0.05,) * 3 + (0.005,) * 3
DRIFT = UnmodeledEffects(
    offset=(1.0, -0.5, 0.8, 0.02, 0.01, -0.02),
    drift=(2.0, 1.0, -1.5, 0.05, 0.0, 0.03),
    drift_time_constant=60.0,
    noise_std=NOISE,
)


def rmse(path: Path) -> dict[int, float]:
    """Contact-force RMSE (N) on ok frames, by number of contacts (1, 2)."""
    tab = pq.read_table(path, columns=["contacts", "status_code"])
    err: dict[int, list] = {1: [], 2: []}
    code = tab.column("status_code").to_numpy()
    for i, row in enumerate(tab.column("contacts").to_pylist()):
        if code[i] or not row:
            continue
        for c in row:
            err[min(len(row), 2)].append(np.subtract(c["force"], c["true_force"]))
    return {k: float(np.sqrt(np.square(v).sum(1).mean())) for k, v in err.items() if v}


def accuracy(model: tc.RobotModel, frames: int, folder: Path) -> None:
    logs = {
        "drift": write_simulated_log(
            model, frames, folder / "drift.parquet", seed=5, effects=DRIFT
        ),
        "clean": write_simulated_log(
            model, frames, folder / "clean.parquet", seed=5,
            effects=UnmodeledEffects(noise_std=NOISE),
        ),
    }  # fmt: skip
    runs = [
        ("no tracking", "drift", {}),
        ("--track-bias (forward-backward)", "drift", {"track_bias": LogBias()}),
        ("--track-bias --no-smoother (causal)", "drift", {"track_bias": LogBias(smoother=False)}),
        ("oracle: no offset, no drift", "clean", {}),
    ]
    print(f"\n{frames} frames at 100 Hz, tcarm base_ft, drift time constant 60 s")
    print("| run | force RMSE, 1 contact (N) | 2 contacts (N) | seconds |")
    print("|---|---:|---:|---:|")
    for name, log, opts in runs:
        out = folder / "out.parquet"
        t0 = time.perf_counter()
        s = estimate_file(logs[log], model, out, progress=False, **opts)
        dt = time.perf_counter() - t0
        r = rmse(out)
        print(
            f"| {name} | {r.get(1, float('nan')):.3f} | {r.get(2, float('nan')):.3f} | {dt:.1f} |"
        )
        if "bias" in s:
            b = s["bias"]["sensors"]["base_ft"]
            print(f"|   bias: contact-free frames {b['contact_free_frames']}, last offset"
                  f" {np.round(b['last'][:3], 3).tolist()} N |  |  |  |")  # fmt: skip
        out.unlink()


def child(log: Path, out: Path, track: bool) -> tuple[float, float]:
    """Wall seconds and peak RSS (MiB, the child's own ``ru_maxrss``) of one ``estimate``."""
    cli = (
        "import resource, sys; from torchcontact.cli import main; rc = main(sys.argv[1:]);"
        " print('MAXRSS', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr);"
        " sys.exit(rc)"
    )
    cmd = [sys.executable, "-c", cli, "estimate", str(log), "--robot", "tcarm",
           "--out", str(out), "--quiet", "--device", "cpu"]  # fmt: skip
    if track:
        cmd.append("--track-bias")
    t0 = time.perf_counter()
    done = subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    dt = time.perf_counter() - t0
    out.unlink()
    rss = [ln for ln in done.stderr.decode().splitlines() if ln.startswith("MAXRSS")]
    return dt, int(rss[-1].split()[1]) / 1024


def memory(model: tc.RobotModel, lengths: list[int], folder: Path) -> None:
    print("\n| frames | run | seconds | peak RSS (MiB) |")
    print("|---:|---|---:|---:|")
    for n in lengths:
        log = write_simulated_log(model, n, folder / f"m{n}.parquet", seed=5, effects=DRIFT)
        for track in (False, True):
            dt, rss = child(log, folder / "o.parquet", track)
            print(f"| {n} | {'--track-bias' if track else 'plain'} | {dt:.1f} | {rss:.0f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20_000, help="accuracy log (default: 20000)")
    ap.add_argument(
        "--long", type=int, default=200_000, help="the longer log of the memory table (200000)"
    )
    ap.add_argument("--sections", nargs="+", default=["accuracy", "memory"])
    args = ap.parse_args()
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if "accuracy" in args.sections:
            accuracy(model, args.frames, folder)
        if "memory" in args.sections:
            memory(model, [args.frames, args.long], folder)


if __name__ == "__main__":
    main()
