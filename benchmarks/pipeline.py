"""End-to-end log pipeline vs in-memory estimator throughput, and peak RSS vs log length.

python benchmarks/pipeline.py [--frames 100000] [--mem 200000 800000]

Bundled tcarm, base F/T sensor, exactly two force contacts per frame (forearm_skin, hand_skin).
Long logs for the memory test are a simulated block tiled with shifted t_ns (streamed writes).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

import torchcontact as tc
from torchcontact.logs import estimate_file, simulated_table
from torchcontact.logs.format import fixed_list
from torchcontact.simulation import simulate


def two_contact_block(model, n):
    log = simulate(model, n, seed=0, max_contacts=2)
    tab = simulated_table(log)
    rng = np.random.default_rng(0)
    links = ["forearm_skin", "hand_skin"] * n
    pos = rng.uniform(-0.03, 0.03, (2 * n, 3)) * [1, 1, 0]
    ctype = tab.schema.field("contacts").type.value_type
    struct = pa.StructArray.from_arrays(
        [
            pa.array(links),
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
    return tab.set_column(tab.schema.get_field_index("contacts"), "contacts", contacts), pos


def write_tiled(model, frames, path, block=50_000):
    tab, _ = two_contact_block(model, min(block, frames))
    with pq.ParquetWriter(path, tab.schema) as w:
        done = 0
        while done < frames:
            n = min(len(tab), frames - done)
            part = tab.slice(0, n)
            part = part.set_column(0, "t_ns", pa.array(part["t_ns"].to_numpy() + done * 10_000_000))
            w.write_table(part, row_group_size=65536)
            done += n


def child(path, out):
    torch.set_num_threads(1)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    s = estimate_file(path, model, out, batch_size=8192, progress=False)
    s["maxrss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(s))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--mem", type=int, nargs=2, default=[200_000, 800_000])
    ap.add_argument("--child", nargs=2)
    a = ap.parse_args()
    if a.child:
        return child(*a.child)
    torch.set_num_threads(1)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    tmp = Path(tempfile.mkdtemp())
    tab, pos = two_contact_block(model, a.frames)
    pq.write_table(tab, tmp / "bench.parquet", row_group_size=65536)
    # in-memory: same frames, same batch size, tensors prepared beforehand
    est = tc.ContactEstimator(model, ["base_ft"])
    col = lambda c: torch.as_tensor(np.stack(tab[c].to_numpy(zero_copy_only=False)))  # noqa: E731
    q, qd, qdd, ft = col("q"), col("qd"), col("qdd"), col("ft.base_ft")
    P = torch.as_tensor(pos.reshape(-1, 2, 3))
    B = 8192
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        for s in range(0, a.frames, B):
            sl = slice(s, s + B)
            est.estimate(
                q[sl],
                qd[sl],
                qdd[sl],
                {"base_ft": ft[sl]},
                tc.Contacts(("forearm_skin", "hand_skin"), ("force", "force"), P[sl]),
            )
        times.append(time.perf_counter() - t0)
    mem_fps = a.frames / np.median(times)
    e2e = []
    for i in range(3):
        t0 = time.perf_counter()
        estimate_file(
            tmp / "bench.parquet", model, tmp / f"out{i}.parquet", batch_size=B, progress=False
        )
        e2e.append(time.perf_counter() - t0)
    e2e_fps = a.frames / np.median(e2e)
    rss = {}
    for n in a.mem:
        path = tmp / f"mem{n}.parquet"
        write_tiled(model, n, path)
        r = subprocess.run(
            [sys.executable, __file__, "--child", str(path), str(tmp / f"memout{n}.parquet")],
            capture_output=True,
            text=True,
            check=True,
        )
        rss[n] = json.loads(r.stdout.strip().splitlines()[-1])["maxrss_mb"]
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    print(
        f"commit {commit}  torch {torch.__version__}  device cpu  threads {torch.get_num_threads()}  {platform.processor() or platform.machine()}"  # noqa: E501
    )
    print("| measure | value |\n|---|---|")
    print(
        f"| in-memory estimator, {a.frames} frames, batch {B} | {mem_fps:,.0f} frames/s (median of 3, spread {min(times):.2f}-{max(times):.2f} s) |"  # noqa: E501
    )
    print(
        f"| end to end Parquet -> estimate -> Parquet | {e2e_fps:,.0f} frames/s (median of 3, spread {min(e2e):.2f}-{max(e2e):.2f} s) |"  # noqa: E501
    )
    print(f"| ratio end-to-end / in-memory | {e2e_fps / mem_fps:.0%} (goal >= 50%) |")
    n0, n1 = a.mem
    print(f"| peak RSS {n0:,} frames | {rss[n0]:.0f} MB |")
    print(f"| peak RSS {n1:,} frames | {rss[n1]:.0f} MB |")
    print(f"| RSS ratio ({n1 // n0}x frames) | {rss[n1] / rss[n0]:.2f}x (goal <= 1.2x) |")


if __name__ == "__main__":
    main()
