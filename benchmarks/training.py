"""Time to fit a correction stack (``python -m training train``) on 36 k frames.

Simulated log (temperature drift + cable, the condition where every layer is fitted), joints of
the sensor; the default configuration: offset, offset + inertial, each with and without the MLP,
chosen on validation blocks, with the 5-fold cross-validated report (``folds 5``) and without it
(``folds 0``: the checkpoint only). Reference in the same process: one contact-free prediction
(``ContactEstimator.predict_ft``) of the same frames, the unit of work every method needs.

Run: ``python benchmarks/training.py [--frames 36000] [--repeat 2]`` from the repository root.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _meta import metadata  # noqa: E402

import torchcontact as tc  # noqa: E402
from training.__main__ import CONDITIONS  # noqa: E402
from training.baselines import predict_free  # noqa: E402
from training.pipeline import Config, DataConfig, make_dataset, resolve_robot, train  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=36000)
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--robots", nargs="+", default=["tcarm:base_ft", "icub:l_arm_ft"])
    args = p.parse_args()
    torch.set_num_threads(1)
    print(metadata())
    print(f"{args.frames} frames, drift + cable, median of {args.repeat} runs\n")
    print("| robot / sensor | predict_ft (reference) | train, folds 0 | train, folds 5 (default) |")
    print("|---|---:|---:|---:|")
    for spec in args.robots:
        robot, sensor = spec.split(":")
        model = tc.RobotModel.from_urdf(resolve_robot(robot))
        data = DataConfig(
            robot=robot, sensor=sensor, frames=args.frames, effects=CONDITIONS["drift+cable"]
        )
        ds = make_dataset(model, data, sensor)
        ds.truth = {}  # a recorded log: no ground truth, the report scores the F/T residual
        ref, times = [], {0: [], 5: []}
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            predict_free(model, sensor, ds.q, ds.qd, ds.qdd)
            ref.append(time.perf_counter() - t0)
            for folds in times:
                torch.manual_seed(0)
                cfg = Config(data=replace(data, folds=folds))
                t0 = time.perf_counter()
                train(model, ds, cfg)
                times[folds].append(time.perf_counter() - t0)
        r = statistics.median(ref)
        cells = [
            f"{statistics.median(v):.1f} s ({statistics.median(v) / r:.0f}x)"
            for v in times.values()
        ]
        print(f"| {model.name} `{sensor}` | {r:.2f} s | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
