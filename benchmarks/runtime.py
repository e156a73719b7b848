"""Latency of the ONNX estimator runtime (one frame) and batched throughput vs the torch estimator.

Usage: python benchmarks/runtime.py [--calls 10000]
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import tempfile
import time

import numpy as np
import onnx
import onnxruntime as ort
import torch

import torchcontact as tc
from torchcontact.export import export_estimator, step_graph_path
from torchcontact.runtime import EstimatorRuntime


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--calls", type=int, default=10000)
    args = p.parse_args()
    links, kinds = ("forearm_skin", "hand_skin"), ("force", "force")
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    path = tempfile.mkdtemp() + "/tcarm.onnx"
    export_estimator(model, None, links, kinds, path, dtype=torch.float32)
    rt = EstimatorRuntime(path)
    rng = np.random.default_rng(0)

    def frames(n):
        f = np.float32
        return dict(
            q=rng.uniform(-1, 1, (n, 7)).astype(f), qd=rng.uniform(-1, 1, (n, 7)).astype(f),
            qdd=rng.uniform(-1, 1, (n, 7)).astype(f), ft=rng.normal(0, 10, (n, 1, 6)).astype(f),
            positions=rng.uniform(-0.05, 0.05, (n, 2, 3)).astype(f), active=np.ones((n, 2), f),
        )  # fmt: skip

    one = {k: v[0] for k, v in frames(1).items()}
    for _ in range(500):
        rt.step(**one)
    lat = np.empty(args.calls)
    for i in range(args.calls):
        t = time.perf_counter_ns()
        rt.step(**one)
        lat[i] = (time.perf_counter_ns() - t) / 1e3
    rows = [("runtime.step, 1 frame, p50 / p99 (us)", f"{np.percentile(lat, 50):.0f} / "
             f"{np.percentile(lat, 99):.0f}")]  # fmt: skip
    nodes = {k: len(onnx.load(str(f)).graph.node) for k, f in
             (("dynamic", path), ("step (N=1)", step_graph_path(path)))}  # fmt: skip
    rows.append(("graph nodes as exported: dynamic / step (N=1)",
                 f"{nodes['dynamic']:,} / {nodes['step (N=1)']:,}"))  # fmt: skip
    est = tc.ContactEstimator(model.to(dtype=torch.float32))
    for n in (1024, 65536):
        x = frames(n)
        t = time.perf_counter()
        rt.run(**x)
        t_onnx = time.perf_counter() - t
        xt = {k: torch.from_numpy(v) for k, v in x.items()}
        c = tc.Contacts(links, kinds, xt["positions"], active=xt["active"] > 0)
        t = time.perf_counter()
        est.estimate(xt["q"], xt["qd"], xt["qdd"], {"base_ft": xt["ft"][:, 0]}, c)
        t_torch = time.perf_counter() - t
        rows.append((f"N={n}: ONNX (1 thread) / torch eigh float32, frames/s",
                     f"{n / t_onnx:,.0f} / {n / t_torch:,.0f}"))  # fmt: skip
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()  # fmt: skip
    print(f"commit {commit}, torch {torch.__version__} ({torch.get_num_threads()} threads), "
          f"onnxruntime {ort.__version__}, {platform.processor() or platform.machine()}, "
          f"graph {rt.metadata['robot']} {rt.metadata['dtype']} opset {rt.metadata['opset']}, "
          f"{rt.metadata['solver']}")  # fmt: skip
    print("| metric | value |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v} |")


if __name__ == "__main__":
    main()
