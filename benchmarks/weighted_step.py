"""The cost of the noise weighting in an exported estimator's single frame (``--ft-noise``).

Exports the bundled arm's estimator (two force slots) four times, float32 and float64, without
and with ``ft_noise`` (0.1 N, 0.005 N m), and times ``EstimatorRuntime.step`` on each in this one
process, the four interleaved in rounds (a noisy moment hurts all alike). Prints the step graph's
node count and the p50 over rounds of the mean step time, and each weighted graph's ratio to the
unweighted one of its dtype.

Run on a quiet machine: ``flock -x /tmp/tc-cpu.lock python benchmarks/weighted_step.py``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import torch

import torchcontact as tc
from torchcontact.export import export_estimator, step_graph_path
from torchcontact.runtime import EstimatorRuntime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=11)
    ap.add_argument("--calls", type=int, default=400, help="steps per round and graph")
    args = ap.parse_args()
    m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    links, kinds = ("forearm_skin", "hand_skin"), ("force", "force")
    rts, nodes = {}, {}
    with tempfile.TemporaryDirectory() as d:
        for dt in ("float32", "float64"):
            for noise in (None, ["base_ft=0.1,0.005"]):
                p = Path(d) / f"{dt}-{bool(noise)}.onnx"
                export_estimator(m, None, links, kinds, p, dtype=getattr(torch, dt),
                                 ft_noise=noise)  # fmt: skip
                key = (dt, "weighted" if noise else "unweighted")
                rts[key] = EstimatorRuntime(p)
                nodes[key] = len(onnx.load(str(step_graph_path(p))).graph.node)
        rng = np.random.default_rng(0)
        q, ft = rng.uniform(-1, 1, m.nv), rng.normal(0, 5, (1, 6))
        pos = rng.uniform(-0.03, 0.03, (2, 3))
        times: dict = {k: [] for k in rts}
        for _ in range(args.rounds):
            for k, rt in rts.items():
                for _ in range(50):  # warm
                    rt.step(q, q, q, ft, positions=pos)
                t = time.perf_counter()
                for _ in range(args.calls):
                    rt.step(q, q, q, ft, positions=pos)
                times[k].append((time.perf_counter() - t) / args.calls * 1e6)
    print("| dtype | solve | step graph nodes | step p50 (µs) | weighted / unweighted |")
    print("| --- | --- | ---: | ---: | ---: |")
    for (dt, w), v in times.items():
        p50 = float(np.median(v))
        ratio = p50 / float(np.median(times[(dt, "unweighted")]))
        print(f"| {dt} | {w} | {nodes[(dt, w)]} | {p50:.1f} | {ratio:.2f} |")


if __name__ == "__main__":
    main()
