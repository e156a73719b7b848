"""Accuracy inside the friction cones, weighted and unweighted, against Bayesian references.

Held-out iCub frames (``benchmarks/_cone_data.py``): 1 to 4 pure forces on the ``l_forearm`` and
``l_hand`` collision meshes pushing inside 0.5 rad cones, ``l_arm_ft`` readings from iDynTree plus
FT 300 noise (0.1 N, 0.005 N m). Per contact count, the median per-contact force error of

* ``pinv``: the paper's ``pinv(A) b`` (unit weights); ``wls``: weighted by the FT 300's noise
  covariance (``ft_covariance=``);
* ``cone min-norm``: ``FrictionCones(objective="min_norm")``, the smallest force inside the cones,
  unweighted and weighted; ``cone MAP``: ``FrictionCones()`` (the default, the maximum a
  posteriori estimate under :class:`torchcontact.constrained.ForcePrior`), unweighted and weighted;

and on a subset of frames (``--ref-frames`` per contact count), beside the weighted estimates:

* ``centre``: the analytic centre of the feasible set (cones, ``|f| <= 40 N``, readings within
  their noise), ``(MAP + centre) / 2`` a weighted combination;
* ``PM vague``: the posterior mean under a vague prior (directions uniform in the cone, ``|f|``
  uniform in [0, 40] N), ``PM oracle``: under the prior that generated the frames, the limit.

Four data sets: magnitudes ``u2-20`` (uniform in [2, 20] N) and ``log`` (log-uniform in
[0.5, 50] N), directions ``uniform`` in the cone and near its ``rim`` (the last 0.1 rad), so that a
prior tuned to one distribution shows. Also: the one-contact tail (p99.9 and max) of the
constrained estimates against the weighted pseudo-inverse; unconverged frames and their status;
a warm start from unrelated frames (``PreviousFrame`` on the shuffled batch) against the cold
answer; and the throughput of the constrained (MAP) estimator over the unconstrained one, both
weighted, timed alternately in this run (generated CPU kernels, one thread).

Run: ``python benchmarks/cones.py [--frames 20000] [--ref-frames 150] [--sets all|main]
[--backend cpu|eager] [--rounds 5] [--throughput-only]`` (iDynTree and icub-models from the
test extra, trimesh from the meshes extra). On a shared machine report the ratios, not the frames/s.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20_000, help="frames of the main data set")
    ap.add_argument("--other-frames", type=int, default=8_000, help="frames of the other sets")
    ap.add_argument("--ref-frames", type=int, default=150, help="reference frames per K >= 2")
    ap.add_argument("--sets", choices=("all", "main"), default="all")
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--steps", type=int, default=20_000, help="Metropolis steps (posterior mean)")
    ap.add_argument("--throughput-only", action="store_true",
                    help="only the throughput rows, main set")  # fmt: skip
    args = ap.parse_args()

    from _cone_data import (
        DIRECTIONS,
        HALF_ANGLE,
        MAGNITUDES,
        SENSOR,
        icub_path,
        make_frames,
        noise_covariance,
        subset,
    )
    from _meta import metadata, rate

    import torchcontact as tc

    torch.set_num_threads(1)
    print(metadata())
    model = tc.RobotModel.from_urdf(icub_path())
    est = tc.ContactEstimator(model, [SENSOR], backend=args.backend)
    cov = {SENSOR: noise_covariance()}
    est_kw = {
        "pinv": {},
        "wls": {"ft_covariance": cov},
        "cone min-norm": {"constraints": tc.FrictionCones(objective="min_norm")},
        "cone min-norm w": {
            "constraints": tc.FrictionCones(objective="min_norm"),
            "ft_covariance": cov,
        },  # fmt: skip
        "cone MAP": {"constraints": tc.FrictionCones()},
        "cone MAP w": {"constraints": tc.FrictionCones(), "ft_covariance": cov},
    }
    sets = [(m, d) for m in MAGNITUDES for d in DIRECTIONS]
    if args.sets == "main" or args.throughput_only:
        sets = sets[:1]
    for si, (mag, dirn) in enumerate(sets):
        n = args.frames if si == 0 else args.other_frames
        t0 = time.perf_counter()
        fr = make_frames(model, n, seed=100 + si, magnitude=mag, direction=dirn)
        print(f"\n## |f| {mag}, directions {dirn} in the {HALF_ANGLE} rad cone: {n} frames"
              f" (iDynTree readings + FT 300 noise, {time.perf_counter() - t0:.0f} s)")  # fmt: skip
        inputs = (fr["q"], fr["qd"], fr["qdd"], fr["ft"], fr["contacts"])
        if args.throughput_only:
            _throughput(est, inputs, cov, args.rounds, rate)
            return
        res = {name: est.estimate(*inputs, **kw) for name, kw in est_kw.items()}
        errs = {name: _errors(r.force, fr) for name, r in res.items()}
        count = fr["count"]
        # ---- reference subset: K >= 2 frames, the first --ref-frames of each count
        ref_idx = np.concatenate([np.flatnonzero(count == K)[: args.ref_frames] for K in (2, 3, 4)])
        refs = _references(est, subset(fr, ref_idx), res["cone MAP w"], ref_idx, mag, dirn,
                           args.steps)  # fmt: skip
        _table(errs, refs, count, ref_idx, fr)
        _tails(errs, count, fr)
        _convergence(res, count)
        if si == 0:
            _warm_start(est, inputs, fr, cov)
            _throughput(est, inputs, cov, args.rounds, rate)


def _errors(force: torch.Tensor, fr: dict) -> np.ndarray:
    """Per-slot force error ``(n, K)`` N, NaN on inactive slots."""
    e = (force - fr["truth"]).norm(dim=-1).numpy()
    return np.where(fr["contacts"].active.numpy(), e, np.nan)


def _med(e: np.ndarray) -> float:
    e = e[np.isfinite(e)]
    return float(np.median(e)) if e.size else float("nan")


def _table(errs, refs, count, ref_idx, fr) -> None:
    names = list(errs)
    print("\nmedian per-contact force error (N) by contacts per frame; gain = pinv / estimator")
    print("| K | frames | " + " | ".join(names) + " |")
    print("|---|---:|" + "---:|" * len(names))
    for K in (1, 2, 3, 4):
        m = count == K
        row = " | ".join(f"{_med(errs[k][m]):.3f}" for k in names)
        print(f"| {K} | {m.sum()} | {row} |")
    m = count >= 3
    base = _med(errs["pinv"][m])
    print(f"| >= 3 | {m.sum()} | " + " | ".join(f"{_med(errs[k][m]):.3f}" for k in names) + " |")
    print("| gain >= 3 | | " + " | ".join(f"{base / _med(errs[k][m]):.2f}x" for k in names) + " |")
    # ---- the subset with the references
    cols = ["pinv", "wls", "cone min-norm w", "cone MAP w", *refs]
    sub = {k: errs[k][ref_idx] for k in cols[:4]} | refs
    cnt = count[ref_idx]
    print(f"\nreference subset ({len(ref_idx)} frames, weighted; gain = pinv / estimator)")
    print("| K | " + " | ".join(cols) + " |")
    print("|---|" + "---:|" * len(cols))
    for K in (2, 3, 4):
        m = cnt == K
        print(f"| {K} | " + " | ".join(f"{_med(sub[k][m]):.3f}" for k in cols) + " |")
    m = cnt >= 3
    base = _med(sub["pinv"][m])
    print("| >= 3 | " + " | ".join(f"{_med(sub[k][m]):.3f}" for k in cols) + " |")
    print("| gain >= 3 | " + " | ".join(f"{base / _med(sub[k][m]):.2f}x" for k in cols) + " |")


def _references(est, sub: dict, map_res, idx, mag: str, dirn: str, steps: int) -> dict:
    """Centre, combination and posterior means on the subset (per-slot errors ``(n, K)``)."""
    from _cone_data import HALF_ANGLE, SENSOR, SIGMA_F, SIGMA_M
    from _cone_refs import ConePrior, contact_matrix, feasible_centre, posterior_mean

    from torchcontact.constrained import cone_rows

    A, r0 = contact_matrix(est, sub)
    w = 1.0 / np.array([SIGMA_F] * 3 + [SIGMA_M] * 3)
    Aw = A * w[None, :, None]
    bw = (sub["ft"][SENSOR].numpy() - r0) * w
    active = sub["contacts"].active.numpy()
    n, K = active.shape
    x_map = map_res.force[torch.as_tensor(idx)].numpy().reshape(n, 3 * K)
    normals = sub["contacts"].normals.numpy()
    mu = float(np.tan(HALF_ANGLE))
    nt = torch.as_tensor(normals)
    C = np.stack([np.array([[float(v) if not torch.is_tensor(v) else v.numpy() for v in row]
                            for row in cone_rows([nt[:, k, j] for j in range(3)], mu)])
                  .transpose(2, 0, 1) for k in range(K)], 1)  # fmt: skip
    resid = ((np.einsum("nri,ni->nr", Aw, x_map) - bw) ** 2).sum(-1)
    chi2 = np.maximum(6.0 + 3.0 * np.sqrt(12.0), 1.5 * resid)[:, None]
    F = max(40.0, 1.2 * float(np.abs(x_map).max()))
    t0 = time.perf_counter()
    centre = feasible_centre(Aw, bw, active, C, F, chi2[:, 0], x_map)
    lo, hi = (0.0, HALF_ANGLE) if dirn == "uniform" else (HALF_ANGLE - 0.1, HALF_ANGLE)
    oracle_mag = ("uniform", 2.0, 20.0) if mag == "u2-20" else ("log", 0.5, 50.0)
    pm_vague, acc_v = posterior_mean(Aw, bw, active, ConePrior(normals, (0.0, HALF_ANGLE),
                                     ("uniform", 0.0, 40.0)), x_map, steps, steps // 3)  # fmt: skip
    pm_oracle, acc_o = posterior_mean(Aw, bw, active, ConePrior(normals, (lo, hi), oracle_mag),
                                      x_map, steps, steps // 3, seed=1)  # fmt: skip
    print(f"references: {n} frames, {time.perf_counter() - t0:.0f} s; Metropolis acceptance"
          f" {acc_v.mean():.2f} (vague), {acc_o.mean():.2f} (oracle)")  # fmt: skip
    truth = sub["truth"].numpy()

    def err(x):
        e = np.linalg.norm(x.reshape(n, K, 3) - truth, axis=-1)
        return np.where(active, e, np.nan)

    return {"centre": err(centre), "(MAP+centre)/2": err(0.5 * (x_map + centre)),
            "PM vague": err(pm_vague), "PM oracle": err(pm_oracle)}  # fmt: skip


def _tails(errs, count, fr) -> None:
    m = count == 1
    print("\none contact: error quantiles (N)")
    print("| estimator | median | p99 | p99.9 | max | p99.9 / wls | max / wls |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    ref = errs["wls"][m]
    ref = ref[np.isfinite(ref)]
    for name in ("pinv", "wls", "cone min-norm w", "cone MAP w", "cone MAP"):
        e = errs[name][m]
        e = e[np.isfinite(e)]
        q = np.quantile(e, [0.5, 0.99, 0.999])
        print(f"| {name} | {q[0]:.3f} | {q[1]:.3f} | {q[2]:.3f} | {e.max():.3f} |"
              f" {q[2] / np.quantile(ref, 0.999):.3f} | {e.max() / ref.max():.3f} |")  # fmt: skip


def _convergence(res, count) -> None:
    from _cone_data import SENSOR

    for name, r in res.items():
        if r.cones is None:
            continue
        conv = r.cones.converged[SENSOR].numpy()
        it = r.cones.iterations[SENSOR].numpy()
        ok = r.status.numpy() == 0
        bad = int((~conv & ok).sum())
        print(f"{name}: converged {conv.mean():.4%}, unconverged marked ok {bad},"
              f" iterations mean {it.mean():.1f} (frames solved {it[it > 0].mean():.1f}), max"
              f" {it.max()}")  # fmt: skip


def _warm_start(est, inputs, fr, cov) -> None:
    """Each frame warm-started from its (unrelated) predecessor: the answers must not change."""
    from _cone_data import SENSOR

    import torchcontact as tc

    for name, kw in (("MAP w", {"ft_covariance": cov}), ("min-norm", {})):
        obj = "map" if name.startswith("MAP") else "min_norm"
        cold = est.estimate(*inputs, constraints=tc.FrictionCones(objective=obj), **kw)
        warm = est.estimate(*inputs, constraints=tc.FrictionCones(objective=obj),
                            warm_start=tc.PreviousFrame(wave=256), **kw)  # fmt: skip
        d = (warm.force - cold.force).norm(dim=-1).numpy()
        conv = warm.cones.converged[SENSOR].numpy()
        ok = warm.status.numpy() == 0
        print(f"warm start from the predecessor ({name}): |warm - cold| max {d.max():.2e} N,"
              f" p99.9 {np.quantile(d, 0.999):.2e} N; unconverged {int((~conv).sum())}, marked ok"
              f" {int((~conv & ok).sum())}")  # fmt: skip


def _throughput(est, inputs, cov, rounds: int, rate) -> None:
    import torchcontact as tc

    n = inputs[0].shape[0]
    kinds = {
        "unconstrained (wls)": {"ft_covariance": cov},
        "constrained (MAP w)": {"ft_covariance": cov, "constraints": tc.FrictionCones()},
        "constrained (min-norm w)": {
            "ft_covariance": cov,
            "constraints": tc.FrictionCones(objective="min_norm"),
        },
    }
    for kw in kinds.values():
        est.estimate(*inputs, **kw)  # build or load the kernels
    rates: dict[str, list[float]] = {k: [] for k in kinds}
    for _ in range(rounds):
        for name, kw in kinds.items():
            rates[name].append(rate(lambda kw=kw: est.estimate(*inputs, **kw), n, 1.0)[0])
    base = rates["unconstrained (wls)"]
    print(f"\nthroughput, {n} frames, backend {est.backend}, 1 thread, {rounds} alternating rounds")
    print("| estimator | frames/s (median) | ratio to unconstrained (median of rounds, range) |")
    print("|---|---:|---:|")
    for name, r in rates.items():
        ratios = [a / b for a, b in zip(r, base, strict=True)]
        print(f"| {name} | {statistics.median(r):,.0f} | {statistics.median(ratios):.2f}"
              f" ({min(ratios):.2f} to {max(ratios):.2f}) |")  # fmt: skip


if __name__ == "__main__":
    main()
