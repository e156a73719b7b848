"""Log pipeline at scale: peak RSS against log length, end-to-end against in-memory throughput,
and the Ray engine next to the local engine.

python benchmarks/pipeline.py [--mem 1000000 10000000] [--ray 200000 --workers 1 2 [--ray-only]]

Bundled tcarm, base F/T sensor, exactly two force contacts per frame (forearm_skin, hand_skin),
chunks of 8192 frames, one torch thread. Long logs are a simulated block of 50 000 frames tiled
with shifted ``t_ns`` (streamed writes). Every measurement runs in its own process, so each peak
RSS (``VmHWM``) is that run's alone:

- ``e2e N``: ``estimate_file`` on an N-frame log (Parquet -> estimate -> Parquet, parts merged).
- ``inmem N``: the same N frames' columns loaded into tensors first (not timed), then
  ``ContactEstimator.estimate`` over chunks of 8192 (the estimator's in-memory throughput).
- ``ray N W``: ``estimate_file_ray`` with W workers on a local Ray instance of W + 1 CPUs (Ray
  start-up included, as a user sees it; the peak RSS is the driver's), and the local engine on
  the same log.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import metadata  # noqa: E402

import torchcontact as tc  # noqa: E402
from torchcontact.logs import estimate_file, simulated_table  # noqa: E402
from torchcontact.logs.format import LogWriter, fixed_list, read_log_columns  # noqa: E402
from torchcontact.simulation import simulate  # noqa: E402

BATCH = 8192
LINKS = ("forearm_skin", "hand_skin")


def two_contact_block(model, n):
    """n simulated frames with exactly two force contacts each (positions in the skin patches)."""
    log = simulate(model, n, seed=0, max_contacts=2)
    tab = simulated_table(log)
    rng = np.random.default_rng(0)
    pos = rng.uniform(-0.03, 0.03, (2 * n, 3)) * [1, 1, 0]
    ctype = tab.schema.field("contacts").type.value_type
    struct = pa.StructArray.from_arrays(
        [
            pa.array(list(LINKS) * n),
            pa.array(["force"] * 2 * n),
            fixed_list(pos),
            pa.nulls(2 * n, ctype.field("direction").type),
            pa.nulls(2 * n, ctype.field("wrench").type),
            pa.nulls(2 * n, ctype.field("true_force").type),
        ],
        fields=list(ctype),
    )
    contacts = pa.ListArray.from_arrays(
        pa.array(np.arange(0, 2 * n + 1, 2, dtype=np.int32)), struct
    )
    return tab.set_column(tab.schema.get_field_index("contacts"), "contacts", contacts)


def write_tiled(model, frames, path, block=50_000):
    """A log of ``frames`` frames: the block repeated with shifted t_ns, written streamed."""
    if path.exists():
        return path
    tab = two_contact_block(model, min(block, frames))
    with LogWriter(path, tab.schema) as w:
        done = 0
        while done < frames:
            n = min(len(tab), frames - done)
            part = tab.slice(0, n)
            part = part.set_column(0, "t_ns", pa.array(part["t_ns"].to_numpy() + done * 10_000_000))
            w.write(part, row_group_size=65536)
            done += n
    return path


def _rss_mb():
    """Peak RSS of this process: VmHWM (ru_maxrss keeps the parent's peak across fork and exec,
    so it would report the writer of the logs, not this run)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child(kind, path, out, workers):
    torch.set_num_threads(1)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    if kind == "e2e":
        s = estimate_file(path, model, out, batch_size=BATCH, progress=False)
        res = {"fps": s["frames_per_s"], "seconds": s["seconds"], "frames": s["frames"]}
    elif kind == "inmem":
        cols = read_log_columns(path, ["q", "qd", "qdd", "ft.base_ft", "contacts"])
        q, qd, qdd, ft = (torch.as_tensor(cols[c]) for c in ("q", "qd", "qdd", "ft.base_ft"))
        P = torch.as_tensor(cols["contacts"].positions.reshape(-1, 2, 3))
        del cols
        est = tc.ContactEstimator(model, ["base_ft"])
        n = len(q)
        t0 = time.perf_counter()
        for s in range(0, n, BATCH):
            sl = slice(s, s + BATCH)
            c = tc.Contacts(LINKS, ("force", "force"), P[sl])
            est.estimate(q[sl], qd[sl], qdd[sl], {"base_ft": ft[sl]}, c)
        sec = time.perf_counter() - t0
        res = {"fps": n / sec, "seconds": sec, "frames": n}
    else:  # ray
        from torchcontact.logs.ray_engine import estimate_file_ray

        s = estimate_file_ray(
            path,
            tc.robots.tcarm_path(),
            out,
            batch_size=BATCH,
            workers=workers,
            num_cpus=workers + 1,
            progress=False,
        )
        res = {"fps": s["frames_per_s"], "seconds": s["seconds"], "frames": s["frames"]}
    res["maxrss_mb"] = _rss_mb()
    print(json.dumps(res))


def run_child(kind, path, out, workers=1):
    Path(out).unlink(missing_ok=True)
    cmd = [sys.executable, __file__, "--child", kind, str(path), str(out), str(workers)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(r.stderr[-3000:])
    Path(out).unlink(missing_ok=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mem", type=int, nargs=2, default=[1_000_000, 10_000_000])
    ap.add_argument("--ray", type=int, default=0, help="frames of the Ray comparison (0: none)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=1, help="runs of each timing (median)")
    ap.add_argument("--ray-only", action="store_true", help="only the Ray comparison")
    ap.add_argument("--tmp", default=None, help="folder for the logs (default: a temp dir)")
    ap.add_argument("--child", nargs=4)
    a = ap.parse_args()
    if a.child:
        return child(a.child[0], a.child[1], a.child[2], int(a.child[3]))
    torch.set_num_threads(1)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    tmp = Path(a.tmp or tempfile.mkdtemp())
    tmp.mkdir(parents=True, exist_ok=True)
    print(metadata())
    print("| run | frames | throughput (frames/s) | seconds | peak RSS (MB) |")
    print("|---|---:|---:|---:|---:|")
    res = {}

    def timed(kind, n, workers=1, label=None):
        path = write_tiled(model, n, tmp / f"log{n}.parquet")
        runs = [run_child(kind, path, tmp / "out.parquet", workers) for _ in range(a.repeat)]
        r = sorted(runs, key=lambda x: x["fps"])[len(runs) // 2]
        r["maxrss_mb"] = max(x["maxrss_mb"] for x in runs)
        label = label or kind
        print(
            f"| {label} | {n:,} | {r['fps']:,.0f} | {r['seconds']:.1f} | {r['maxrss_mb']:.0f} |",
            flush=True,
        )
        res[(label, n)] = r
        return r

    if a.ray:
        timed("e2e", a.ray, label="local engine")
        for w in a.workers:
            timed("ray", a.ray, w, label=f"ray, {w} worker(s)")
    if a.ray_only:
        return
    n0, n1 = a.mem
    small, big = timed("e2e", n0), timed("e2e", n1)
    mem = timed("inmem", n1)
    print()
    print("| goal | measured |")
    print("|---|---|")
    print(
        f"| peak RSS {n1:,} / {n0:,} frames <= 1.2 | {big['maxrss_mb'] / small['maxrss_mb']:.2f}"
        f" ({big['maxrss_mb']:.0f} / {small['maxrss_mb']:.0f} MB) |"
    )
    print(
        f"| end-to-end / in-memory throughput at {n1:,} frames >= 50% |"
        f" {big['fps'] / mem['fps']:.0%} ({big['fps']:,.0f} / {mem['fps']:,.0f} frames/s) |"
    )


if __name__ == "__main__":
    main()
