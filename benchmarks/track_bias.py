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

3. **Filter**: ``BiasSmoother`` alone (forward pass in chunks of 65,536 frames, then the
   smoother), µs per frame, this tree against the package of ``--before`` (the per-frame loops
   in Python) imported beside it, one process, on the same residuals (one sensor, 30 % of the
   frames in contact); the offsets of both agree (printed).

Run: ``python benchmarks/track_bias.py [--frames 20000] [--long 200000] [--sections accuracy
memory filter]`` (the numbers of docs/online.md were taken on a shared 2-core machine: compare
within a table).
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


def filter_time(frames: int, before: str, folder: Path) -> None:
    """Section 3: the bias filter and smoother alone, this tree against ``before``."""
    import importlib

    from _meta import load_old_package

    from torchcontact.online.bias import BiasSmoother

    old = importlib.import_module(f"{load_old_package(before, folder).__name__}.online.bias")
    rng = np.random.default_rng(0)
    z = rng.normal(0.0, 0.05, (frames, 1, 6)) + np.linspace(0.0, 3.0, frames)[:, None, None]
    free = rng.random(frames) > 0.3
    t = np.arange(frames) * 0.01
    rows, offs = [], []
    for name, cls in ((f"{before} (per-frame loops)", old.BiasSmoother),
                      ("this tree (scans)", BiasSmoother)):  # fmt: skip
        best = float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            sm = cls(1, time_constant=0.5, period=0.01)
            for a in range(0, frames, 65536):
                sm.forward(z[a : a + 65536], free[a : a + 65536], t[a : a + 65536])
            t1 = time.perf_counter()
            sm.smooth()
            t2 = time.perf_counter()
            if t2 - t0 < best:
                best, fwd, bwd = t2 - t0, t1 - t0, t2 - t1
        offs.append(sm.offsets(0, frames)[0])
        rows.append((name, 1e6 * fwd / frames, 1e6 * bwd / frames))
    print(f"\n3. BiasSmoother alone, {frames:,} frames, one sensor (best of 3, µs per frame)\n")
    print("| version | forward | smoother | total | speed-up |\n|---|---:|---:|---:|---:|")
    ref = rows[0][1] + rows[0][2]
    for name, f, b in rows:
        print(f"| {name} | {f:.2f} | {b:.2f} | {f + b:.2f} | {ref / (f + b):.1f}x |")
    print(f"\nlargest offset difference: {float(np.abs(offs[0] - offs[1]).max()):.2e} N")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20_000, help="accuracy log (default: 20000)")
    ap.add_argument(
        "--long", type=int, default=200_000, help="the longer log of the memory table (200000)"
    )
    ap.add_argument("--sections", nargs="+", default=["accuracy", "memory", "filter"])
    ap.add_argument("--before", default="6cb60c8", help="section 3's earlier commit")
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
        if "filter" in args.sections:
            filter_time(args.long, args.before, folder)


if __name__ == "__main__":
    main()
