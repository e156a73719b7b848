"""Friction-cone constrained estimation vs the unconstrained estimator, same frames, same run.

Whole iCubGenova04 (icub-models), all six F/T sensors, 4 pure forces in the left arm region
(2 on l_forearm, 2 on l_hand) pushing inside 0.5 rad cones, float64, generated CPU kernels
(built before timing; the build time is printed), ``torch.utils.benchmark`` medians. Also prints
the median force error of both estimates against the truth.

Run: ``python benchmarks/constrained.py [--frames 20000] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
import torch.utils.benchmark as tbench

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import metadata  # noqa: E402

import torchcontact as tc  # noqa: E402

LINKS = ("l_forearm", "l_forearm", "l_hand", "l_hand")


def frames(model, est, n, seed=0):
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    q, qd, qdd = ((torch.rand(n, model.nv, generator=g, dtype=f64) * 2 - 1) for _ in range(3))
    pos = (torch.rand(n, 4, 3, generator=g, dtype=f64) - 0.5) * torch.tensor([0.03, 0.03, 0.1],
                                                                          dtype=f64)  # fmt: skip
    nrm = torch.randn(n, 4, 3, generator=g, dtype=f64)
    nrm = nrm / nrm.norm(dim=-1, keepdim=True)
    t = torch.randn(n, 4, 3, generator=g, dtype=f64)
    t = t - (t * nrm).sum(-1, keepdim=True) * nrm
    t = t / t.norm(dim=-1, keepdim=True)
    ang = 0.5 * torch.rand(n, 4, 1, generator=g, dtype=f64)
    f = 10 * torch.rand(n, 4, 1, generator=g, dtype=f64) * (-torch.cos(ang) * nrm
                                                            + torch.sin(ang) * t)  # fmt: skip
    wr = torch.cat([f, 0 * f], -1)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(LINKS, ("known",) * 4, pos, wrenches=wr))
    return (q, qd, qdd, ft), tc.Contacts(LINKS, ("force",) * 4, pos, normals=nrm,
                                         cone_angle=0.5), f  # fmt: skip


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=20_000)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--iterations", type=int, default=20)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    import icub_models

    model = tc.RobotModel.from_urdf(icub_models.get_model_file("iCubGenova04"))
    est = tc.ContactEstimator(model, backend="cpu")
    state, c, truth = frames(model, est, args.frames)
    cons = tc.FrictionCones(iterations=args.iterations)
    print(metadata())
    for name, kw in (("unconstrained", {}), ("constrained", {"constraints": cons})):
        t0 = time.perf_counter()
        est.estimate(*(x[:16] for x in state[:3]), {k: v[:16] for k, v in state[3].items()},
                     tc.Contacts(c.links, c.kinds, c.positions[:16], normals=c.normals[:16],
                                 cone_angle=0.5), **kw)  # fmt: skip
        print(f"{name}: kernel build or load {time.perf_counter() - t0:.1f} s")
    res = {}
    for name, kw in (("unconstrained", {}), ("constrained", {"constraints": cons})):
        tm = tbench.Timer("est.estimate(*state, c, **kw)",
                          globals=dict(est=est, state=state, c=c, kw=kw))  # fmt: skip
        m = tm.blocked_autorange(min_run_time=3.0)
        out = est.estimate(*state, c, **kw)
        err = (out.force - truth).norm(dim=-1).median().item()
        res[name] = (args.frames / m.median, err, out)
        print(f"{name:>14}: {args.frames / m.median:>12,.0f} frames/s (median of {len(m.times)},"
              f" IQR {m.iqr / m.median:.1%}), median force error {err:.3f} N")  # fmt: skip
    ratio = res["constrained"][0] / res["unconstrained"][0]
    cones = res["constrained"][2].cones
    print(f"throughput constrained / unconstrained: {ratio:.1%} (goal >= 20%)")
    print(f"median error pinv / constrained: {res['unconstrained'][1] / res['constrained'][1]:.2f}x"
          f"; converged {cones.converged['l_arm_ft'].float().mean():.1%}, iterations median"
          f" {cones.iterations['l_arm_ft'].median().item()} max"
          f" {cones.iterations['l_arm_ft'].max().item()}")  # fmt: skip


if __name__ == "__main__":
    main()
