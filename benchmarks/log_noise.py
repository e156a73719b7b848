"""``torchcontact estimate`` weighted by the F/T noise, and the cost of the cone checks, on a log.

Run (a quiet machine for the frames/s; the errors do not depend on it)::

    python benchmarks/log_noise.py                 # 20,000 frames of the tcarm, FT 300 noise
    python benchmarks/log_noise.py --frames 4000   # quicker

The log: :func:`torchcontact.logs.write_simulated_log` of the bundled tcarm (seed 0), 1-2 pushing
forces per contact stretch on the skin, readings with the FT 300 datasheet noise (0.1 N, 0.005
N m). Every row estimates the same log with :func:`torchcontact.logs.estimate_file` (kernels in
the cache: one untimed run first, which waits for its kernels), in this process, rows
alternating over ``--rounds``:

- ``unweighted``: ``--unweighted``, the paper's ``pinv(A) b``;
- ``weighted, contact-free estimate``: no noise given (estimated from the contact-free frames);
- ``weighted, datasheet``: ``--ft-noise base_ft=robotiq-ft300``;
- ``constrained`` rows (``--constraints --friction MU``, MAP): their frames/s include the
  unconstrained solve the outside-cone count needs.

Errors: force error of the frames with one contact and ``rank == unknowns`` against the
simulator's ``true_force`` (median, p95, p99.9).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import metadata  # noqa: E402

STD = (0.1, 0.1, 0.1, 0.005, 0.005, 0.005)


def _errors(out: Path) -> np.ndarray:
    import pyarrow.parquet as pq

    tab = pq.read_table(out)
    well = tab["rank.base_ft"].to_numpy() == tab["unknowns.base_ft"].to_numpy()
    rows = tab["contacts"].to_pylist()
    return np.array([
        np.linalg.norm(np.subtract(r[0]["force"], r[0]["true_force"]))
        for r, w in zip(rows, well, strict=True) if w and len(r) == 1
    ])  # fmt: skip


def main() -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20_000, help="frames of the log (default: 20000)")
    ap.add_argument("--rounds", type=int, default=3, help="timed rounds per row (default: 3)")
    ap.add_argument("--friction", type=float, default=1.0, help="--friction of the cone rows")
    args = ap.parse_args()

    import torch

    import torchcontact as tc
    from torchcontact.logs import LogConstraints, estimate_file, pipeline, write_simulated_log
    from torchcontact.simulation import UnmodeledEffects

    torch.set_num_threads(1)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    tmp = Path(tempfile.mkdtemp())
    log = write_simulated_log(model, args.frames, tmp / "log.parquet", seed=0,
                              effects=UnmodeledEffects(noise_std=STD))  # fmt: skip
    cones = LogConstraints(friction=args.friction)
    rows = {
        "unweighted": {"unweighted": True},
        "weighted, contact-free estimate": {},
        "weighted, datasheet": {"ft_noise": ["base_ft=robotiq-ft300"]},
        "constrained, unweighted": {"unweighted": True, "constraints": cones},
        "constrained, weighted (contact-free)": {"constraints": cones},
    }
    times: dict[str, list[float]] = {k: [] for k in rows}
    summaries = {}
    pipeline.WAIT_FOR_KERNEL_FRAMES = 0  # untimed: waits for the kernels to be built
    for k, kw in rows.items():
        summaries[k] = estimate_file(log, model, tmp / "warm.parquet", **kw)
        (tmp / "warm.parquet").unlink()
    pipeline.WAIT_FOR_KERNEL_FRAMES = None
    for r in range(args.rounds):
        for k, kw in rows.items():
            out = tmp / f"{r}.parquet"
            t0 = time.perf_counter()
            estimate_file(log, model, out, **kw)
            times[k].append(time.perf_counter() - t0)
            if r == args.rounds - 1:
                summaries[k]["errors"] = _errors(out)
            out.unlink()
    print(metadata())
    print(f"\n{args.frames} tcarm frames, FT 300 noise; cone rows --friction {args.friction}\n")
    print("| estimate | noise | 1-contact median (N) | p95 | p99.9 | frames/s | ratio |")
    print("|---|---|---:|---:|---:|---:|---:|")
    base = args.frames / statistics.median(times["unweighted"])
    for k in rows:
        e, s = summaries[k]["errors"], summaries[k]
        fps = args.frames / statistics.median(times[k])
        noise = s["noise"]
        src = noise["sensors"]["base_ft"]["source"] if noise["weighted"] else "unweighted"
        q = np.percentile(e, [50, 95, 99.9])
        print(f"| {k} | {src} | {q[0]:.3f} | {q[1]:.3f} | {q[2]:.3f} | {fps:,.0f} |"
              f" {fps / base:.2f} |")  # fmt: skip
    for k in ("constrained, unweighted", "constrained, weighted (contact-free)"):
        print(f"\n{k}: cones {summaries[k]['cones']}")


if __name__ == "__main__":
    main()
