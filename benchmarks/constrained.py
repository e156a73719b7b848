"""Friction-cone constrained estimation vs the unconstrained estimator, same frames, same run.

Whole iCubGenova04 (icub-models), all six F/T sensors, K = 4 pure forces in the left arm region
(``examples/cone_experiment.py``: forearm and hand, pushing inside 0.5 rad cones, |f| <= 10 N),
float64, generated CPU kernels (built before timing; with ``--cold-build`` in an empty kernel
cache, so the printed time is a real build), ``torch.utils.benchmark`` medians.

The two estimators are timed alternately, ``--rounds`` times, and the throughput ratio is taken
per round (a shared machine's load then hits both alike); the table gives the median ratio and
its range. Also printed: the size of both programs (operations of the traced SSA graph; for the
constrained one, those of one interior-point iteration, which the kernel loops over), the
iterations the frames ran (mean, max, and the mean over vector blocks of four frames of the
slowest frame: what the kernel pays), and the median force error of both estimates.

With ``--log N``, also the log pipeline's warm start (``estimate --constraints``): a simulated
iCub log of N frames (``torchcontact.simulation``: up to four contacts on l_forearm and l_hand,
held 0.3 to 3 s, pushing within 0.62 rad of their skin normal, cones of 0.7 rad), estimated with
each frame started from its predecessor's estimate and with every frame started cold: the
iterations the solver ran (mean over the frames it solved) and the frames/s of the whole
pipeline (kernels built by a first run).

Run on a quiet machine: ``flock -x /tmp/tc-cpu.lock python benchmarks/constrained.py
[--frames 20000] [--threads 1] [--rounds 5] [--cold-build] [--log 100000]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20_000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=None, help="budget (default FrictionCones)")
    ap.add_argument("--cold-build", action="store_true", help="build the kernels in a new cache")
    ap.add_argument("--log", type=int, default=0, metavar="N", help="warm start on an N-frame log")
    args = ap.parse_args()
    if args.cold_build:
        os.environ["TORCHCONTACT_CACHE"] = tempfile.mkdtemp(prefix="tc-bench-cache-")

    import torch
    from _meta import metadata, rate
    from cone_experiment import LINKS, icub_model, simulate

    import torchcontact as tc
    from torchcontact.estimation.programs import program
    from torchcontact.kernels._cpp import live_nodes, loop_bodies

    torch.set_num_threads(args.threads)
    model = icub_model()
    est = tc.ContactEstimator(model, backend="cpu")
    K = 4
    state, c, truth = simulate(model, est, K, args.frames, seed=0)
    sensor = est.sensor_names[est.region[model.frame(LINKS[0]).body]]
    cons = tc.FrictionCones() if args.iterations is None else tc.FrictionCones(args.iterations)
    kinds = {"unconstrained": {}, "constrained": {"constraints": cons}}
    print(metadata())
    print(f"iCub, {K} force contacts ({', '.join(LINKS[:K])}), {args.frames} frames, float64,"
          f" budget {cons.iterations} iterations")  # fmt: skip
    em = est.layout(c.links, c.kinds)
    for name, kw in kinds.items():
        flags = None if not kw else kw["constraints"].program_flags(torch.float64)
        tr, out = program(em, "estimate", False, False, False, flags, False, False).trace()
        nodes = live_nodes(tr, [x for xs in out.values() for x in xs])
        body = sum(len(b) for b in loop_bodies(nodes).values())
        t0 = time.perf_counter()
        small = tc.Contacts(c.links, c.kinds, c.positions[:16], normals=c.normals[:16],
                            cone_angle=c.cone_angle)  # fmt: skip
        est.estimate(*(x[:16] for x in state[:3]), {k: v[:16] for k, v in state[3].items()},
                     small, **kw)  # fmt: skip
        what = "build" if args.cold_build else "build or load"
        print(f"{name:>14}: {len(nodes):,} operations" + (f" ({body:,} per iteration)" if body
              else "") + f"; kernel {what} {time.perf_counter() - t0:.1f} s")  # fmt: skip
    rates: dict[str, list[float]] = {k: [] for k in kinds}
    ratios = []
    for _ in range(args.rounds):
        for name, kw in kinds.items():
            fps, _ = rate(lambda kw=kw: est.estimate(*state, c, **kw), args.frames, 1.0)
            rates[name].append(fps)
        ratios.append(rates["constrained"][-1] / rates["unconstrained"][-1])
    res = {name: est.estimate(*state, c, **kw) for name, kw in kinds.items()}
    print("| estimator | frames/s (median of rounds) | median force error (N) |")
    print("|---|---:|---:|")
    for name in kinds:
        err = (res[name].force - truth).norm(dim=-1).median().item()
        print(f"| {name} | {statistics.median(rates[name]):,.0f} | {err:.3f} |")
    print(f"throughput constrained / unconstrained: {statistics.median(ratios):.1%} (rounds:"
          f" {min(ratios):.1%} to {max(ratios):.1%}; goal >= 20%)")  # fmt: skip
    cones = res["constrained"].cones
    it = cones.iterations[sensor].double()
    block = it[: len(it) // 4 * 4].reshape(-1, 4).amax(-1)
    print(f"iterations: mean {it.mean():.1f}, max {int(it.max())}, slowest of each block of 4"
          f" frames {block.mean():.1f} on average; converged"
          f" {cones.converged[sensor].double().mean():.2%}; cones active"
          f" {cones.active.double().mean():.0%}")  # fmt: skip
    e_free = (res["unconstrained"].force - truth).norm(dim=-1).median().item()
    e_cone = (res["constrained"].force - truth).norm(dim=-1).median().item()
    print(f"median error pinv / constrained: {e_free / e_cone:.2f}x")
    if args.log:
        log_warm_start(model, args.log)


def log_warm_start(model, frames: int) -> None:
    """Warm vs cold starts of ``estimate --constraints`` on a simulated iCub log."""
    import math

    from torchcontact.logs import estimate_file
    from torchcontact.logs.pipeline import LogConstraints
    from torchcontact.logs.simlog import write_simulated_log

    d = Path(tempfile.mkdtemp(prefix="tc-bench-log-"))
    log = write_simulated_log(model, frames, d / "log.parquet", sensor="l_arm_ft",
                              links=["l_forearm", "l_hand"], max_contacts=4, seed=1)  # fmt: skip
    print(f"log: {frames} frames, iCub l_arm_ft, up to 4 contacts on l_forearm and l_hand")
    from torchcontact import kernels

    runs = []
    for i, warm in enumerate((True, False, True, False)):
        if i == 2:  # the first two runs start the kernels' builds (backend "auto"): finish them
            kernels.wait_for_builds()
        out = d / f"est-{warm}.parquet"
        out.unlink(missing_ok=True)
        cons = LogConstraints(friction=math.tan(0.7), warm_start=warm)
        runs.append((warm, estimate_file(log, model, out, constraints=cons, progress=False)))
    print("| start | frames/s (pipeline) | frames solved | iterations mean | max | converged |")
    print("|---|---:|---:|---:|---:|---:|")
    for warm, s in runs[2:]:
        c = s["cones"]
        print(f"| {'predecessor' if warm else 'cold (pinv)'} | {s['frames_per_s']:,.0f} |"
              f" {c['solved']} | {c['iterations_mean']:.2f} | {c['iterations_max']} |"
              f" {c['converged']:.2%} |")  # fmt: skip


if __name__ == "__main__":
    main()
