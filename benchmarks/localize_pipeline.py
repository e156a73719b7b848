"""Throughput of ``estimate --localize`` against ``estimate`` with skin, on the same log.

One simulated iCub log (``l_arm_ft``, one contact at a time on the ``l_forearm`` and ``l_hand``
collision meshes) is written twice: with the contacts in ``contacts`` (skin) and without
(``--no-skin``: the truth in ``true_contacts``). Each row of the table is the local engine's
whole run (``torchcontact.logs.estimate_file``: read, decode, localize, estimate, write), in one
process, after a warm-up run of every configuration (kernels built and cached), so the ratios
to the skin run compare like with like. The second table splits the localizing run's time by
stage (timers around the pipeline's functions, on the estimating thread).

    python benchmarks/localize_pipeline.py [--frames 20000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import metadata  # noqa: E402

LINKS = ["l_forearm", "l_hand"]


def timers(ray: str):
    """Wrap the pipeline's stages with accumulating timers; returns (totals, restore)."""
    import torchcontact.localize as L
    from torchcontact.logs import chunks

    totals: dict[str, float] = defaultdict(float)
    saved = []

    def wrap(owner, name, label):
        fn = getattr(owner, name)
        saved.append((owner, name, fn))

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                totals[label] += time.perf_counter() - t0

        setattr(owner, name, timed)
        totals[label] = 0.0  # (rows in this order)

    wrap(chunks.LogEstimator, "localized", "localization in the pipeline (all of it)")
    wrap(L, "localize_chunk", "  localize_chunk")
    wrap(L, "run_program", "    line program (b and link poses)")
    wrap(L.Localizer, "localize_wrench", "    localize_wrench (stages 2-5)")
    wrap(L, "cast_embree" if ray == "embree" else "cast_bvh", f"      ray casting ({ray})")
    wrap(L, "select_entries", "      selection")
    wrap(L, "_point_covariance", "      covariance")
    wrap(chunks.LogEstimator, "_solve", "the estimator (A x = b)")

    def restore():
        for owner, name, fn in reversed(saved):
            setattr(owner, name, fn)

    return totals, restore


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=20000, help="frames of the log")
    ap.add_argument("--batch-size", type=int, default=8192, help="frames per chunk")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per configuration")
    ap.add_argument("--ft-std", action="store_true", help="also the position std (covariance)")
    args = ap.parse_args()
    torch.set_num_threads(1)  # as the CLI (--threads 1)
    import icub_models

    import torchcontact as tc
    from torchcontact import kernels
    from torchcontact.localize import embree_available
    from torchcontact.logs import estimate_file, write_simulated_log
    from torchcontact.logs.pipeline import LogLocalize
    from torchcontact.meshes import load_meshes

    urdf = icub_models.get_model_file("iCubGenova04")
    model = tc.RobotModel.from_urdf(urdf)
    meshes = load_meshes(model, urdf, "collision", links=LINKS)
    tmp = Path(tempfile.mkdtemp(prefix="tc-locpipe-"))
    logs = {}
    for skin in (True, False):
        logs[skin] = write_simulated_log(
            model, args.frames, tmp / f"{'skin' if skin else 'noskin'}.parquet", seed=0,
            sensor="l_arm_ft", links=LINKS, max_contacts=1, surface=meshes.links, skin=skin,
            temperature=False,
        )  # fmt: skip
    std = [0.1] * 3 + [0.005] * 3 if args.ft_std else None
    rays = ["torch"] + (["embree"] if embree_available() else [])
    configs = {"estimate, skin contacts (reference)": (logs[True], None, True)}
    for ray in rays:
        loc = LogLocalize(meshes, LINKS, ray=ray, ft_std=std)
        configs[f"estimate --localize, no skin, ray={ray}"] = (logs[False], loc, True)
        configs[f"estimate --localize, no skin, ray={ray}, on the estimating thread"] = (
            logs[False], loc, False
        )  # fmt: skip
    kw = dict(sensors=["l_arm_ft"], batch_size=args.batch_size)

    from torchcontact.logs import chunks

    def run(name, k):
        log, loc, on_reader = configs[name]
        out = tmp / f"out-{k}.parquet"
        chunks.LOCALIZE_ON_READER = on_reader  # localize on the reader thread (the default)
        s = estimate_file(log, model, out, localize=loc, **kw)
        out.unlink()
        return s

    for k, name in enumerate(configs):  # warm-up: kernels built and loaded, meshes cached
        run(name, k)
        kernels.wait_for_builds()
        run(name, k)
    rates: dict[str, list[float]] = defaultdict(list)
    summaries = {}
    for _ in range(args.repeats):  # interleaved: load changes hit every configuration alike
        for k, name in enumerate(configs):
            s = run(name, k)
            rates[name].append(s["frames"] / s["seconds"])
            summaries[name] = s
    print(f"`python benchmarks/localize_pipeline.py --frames {args.frames}` ({metadata()})")
    print()
    ref = float(np.median(rates[next(iter(configs))]))
    print("| run | frames/s (median) | ratio to the skin run | localized frames |")
    print("| --- | ---: | ---: | ---: |")
    for name in configs:
        r = float(np.median(rates[name]))
        loc = summaries[name].get("localize", {}).get("l_arm_ft", {}).get("localized", "-")
        print(f"| {name} | {r:,.0f} | {r / ref:.2f}x | {loc} |")
    for ray in rays:
        name = f"estimate --localize, no skin, ray={ray}"
        totals, restore = timers(ray)
        t0 = time.perf_counter()
        run(name, 99)
        wall = time.perf_counter() - t0
        restore()
        print()
        print(f"Stages of one `{name}` run ({args.frames} frames, {wall:.2f} s wall):")
        print()
        print("| stage | s | share of the run |")
        print("| --- | ---: | ---: |")
        for label, sec in totals.items():
            lead = len(label) - len(label.lstrip())
            name_md = "&nbsp;" * lead + label.lstrip()
            print(f"| {name_md} | {sec:.2f} | {100 * sec / wall:.0f} % |")


if __name__ == "__main__":
    main()
