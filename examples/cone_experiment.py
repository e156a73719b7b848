"""The paper's statistical analysis (Del Prete et al. 2012, Sec. 3) for 2 to 6 pushing contacts.

iCub (icub-models) left forearm and hand, behind the left arm F/T sensor: K = 2, 3, 4 and 6 pure
forces, each pushing inside a cone of half-angle 0.5 rad around the inward surface normal (angle
uniform in [0, 0.5] rad, norm uniform in [0, F] N), random joint states, exact readings. Per force
the error norm of the pseudo-inverse (the paper's estimate) and of the friction-cone constrained
estimates (``estimate(..., constraints=FrictionCones())``, the maximum a posteriori default, and
``FrictionCones(objective="min_norm")``; same normals, same 0.5 rad cones); like
the paper's sigma ~ K/4 analysis, errors are summarised by their RMS (sigma of a half-Gaussian) in
units of the maximum force F, the median, and the shares below F/4 and F/2.

Usage: ``python examples/cone_experiment.py [--frames 4000] [--F 10] [--out cone_hist.png]``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

import torchcontact as tc

LINKS = ("l_forearm", "l_forearm", "l_hand", "l_forearm", "l_hand", "l_hand")
HALF_ANGLE = 0.5


def icub_model() -> tc.RobotModel:
    """The iCubGenova04 model from the ``icub-models`` package."""
    import icub_models

    return tc.RobotModel.from_urdf(icub_models.get_model_file("iCubGenova04"))


def simulate(
    model: tc.RobotModel, est: tc.ContactEstimator, K: int, frames: int, F: float = 10.0,
    seed: int = 0,
) -> tuple[tuple, tc.Contacts, torch.Tensor]:  # fmt: skip
    """Random joint states and ``K`` pushing forces per frame, and the readings they cause.

    Args:
        model: the iCub.
        est: its estimator (all sensors).
        K: contacts per frame (on ``LINKS[:K]``).
        frames: number of frames.
        F: maximum force norm, N.
        seed: random seed.

    Returns:
        ``((q, qd, qdd, ft), contacts, truth)``: the estimator's inputs, the ``force`` slots with
        their normals and 0.5 rad cones, and the true forces ``(frames, K, 3)`` (link frames).
    """
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    links = LINKS[:K]
    q, qd, qdd = ((torch.rand(frames, model.nv, generator=g, dtype=f64) * 2 - 1) for _ in range(3))
    pos = (torch.rand(frames, K, 3, generator=g, dtype=f64) - 0.5) * torch.tensor(
        [0.03, 0.03, 0.1], dtype=f64
    )
    normals = torch.randn(frames, K, 3, generator=g, dtype=f64)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    t = torch.randn(frames, K, 3, generator=g, dtype=f64)
    t = t - (t * normals).sum(-1, keepdim=True) * normals
    t = t / t.norm(dim=-1, keepdim=True)
    ang = HALF_ANGLE * torch.rand(frames, K, 1, generator=g, dtype=f64)
    norm = F * torch.rand(frames, K, 1, generator=g, dtype=f64)
    truth = norm * (-torch.cos(ang) * normals + torch.sin(ang) * t)
    wr = torch.cat([truth, torch.zeros_like(truth)], -1)
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(links, ("known",) * K, pos, wrenches=wr))
    c = tc.Contacts(links, ("force",) * K, pos, normals=normals, cone_angle=HALF_ANGLE)
    return (q, qd, qdd, ft), c, truth


def run(model: tc.RobotModel, K: int, frames: int, F: float = 10.0, seed: int = 0,
        backend: str = "auto") -> dict[str, np.ndarray]:  # fmt: skip
    """Simulate ``K`` pushing forces per frame (:func:`simulate`) and estimate them both ways.

    Args:
        model: the iCub.
        K: contacts per frame (on ``LINKS[:K]``).
        frames: number of frames.
        F: maximum force norm, N.
        seed: random seed.
        backend: kernel backend of the estimator.

    Returns:
        ``pinv``, ``cone`` (the default, MAP) and ``cone_min_norm`` error norms ``(frames, K)``
        N, ``converged`` ``(frames,)`` (both constrained estimates), ``iterations``
        ``(frames,)`` (MAP), ``active`` ``(frames, K)`` (the min-norm estimate's binding
        cones: the MAP estimate is interior), ``rank`` and ``unknowns``.
    """
    est = tc.ContactEstimator(model)
    sensor = est.sensor_names[est.region[model.frame(LINKS[0]).body]]
    (q, qd, qdd, ft), c, truth = simulate(model, est, K, frames, F, seed)
    free = est.estimate(q, qd, qdd, ft, c, backend=backend)
    cone = est.estimate(q, qd, qdd, ft, c, constraints=tc.FrictionCones(), backend=backend)
    mn = est.estimate(q, qd, qdd, ft, c, constraints=tc.FrictionCones(objective="min_norm"),
                      backend=backend)  # fmt: skip
    return {
        "pinv": (free.force - truth).norm(dim=-1).numpy(),
        "cone": (cone.force - truth).norm(dim=-1).numpy(),
        "cone_min_norm": (mn.force - truth).norm(dim=-1).numpy(),
        "converged": cone.cones.converged[sensor].numpy() & mn.cones.converged[sensor].numpy(),
        "iterations": cone.cones.iterations[sensor].numpy(),
        "active": mn.cones.active.numpy(),
        "rank": free.rank[sensor].numpy(),
        "unknowns": free.unknowns[sensor].numpy(),
    }


def summary(error: np.ndarray, F: float) -> dict[str, float]:
    """RMS (half-Gaussian sigma) and median in units of F, shares below F/4 and F/2."""
    e = error.ravel()
    return {
        "sigma_over_F": float(np.sqrt(np.mean(e**2)) / F),
        "median_over_F": float(np.median(e) / F),
        "below_F_4": float(np.mean(e < F / 4)),
        "below_F_2": float(np.mean(e < F / 2)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=4000)
    ap.add_argument("--F", type=float, default=10.0)
    ap.add_argument("--out", default="cone_hist.png")
    args = ap.parse_args()
    model = icub_model()
    rows, results = [], {}
    for K in (2, 3, 4, 6):
        r = run(model, K, args.frames, args.F)
        results[K] = r
        sp, sc = summary(r["pinv"], args.F), summary(r["cone"], args.F)
        sm = summary(r["cone_min_norm"], args.F)
        rows.append(
            f"| {K} | {int(np.median(r['unknowns']))} / {int(np.median(r['rank']))} |"
            f" {sp['sigma_over_F']:.3f} | {sm['sigma_over_F']:.3f} | {sc['sigma_over_F']:.3f} |"
            f" {sp['median_over_F']:.3f} | {sm['median_over_F']:.3f} |"
            f" {sc['median_over_F']:.3f} |"
            f" {sp['median_over_F'] / max(sm['median_over_F'], 1e-12):.1f}x /"
            f" {sp['median_over_F'] / max(sc['median_over_F'], 1e-12):.1f}x |"
            f" {100 * sp['below_F_4']:.0f}% / {100 * sm['below_F_4']:.0f}% /"
            f" {100 * sc['below_F_4']:.0f}% |"
            f" {100 * r['converged'].mean():.1f}% | {np.median(r['iterations']):.0f}"
            f" ({r['iterations'].max()}) | {100 * r['active'].mean():.0f}% |"
        )
    print(f"iCub left arm, {args.frames} frames per K, |f| ~ U[0, {args.F:g}] N, pushing within "
          f"{HALF_ANGLE} rad of the normal, exact readings")  # fmt: skip
    print("| K | unknowns / rank | sigma/F pinv | min-norm | MAP | median/F pinv | min-norm |"
          " MAP | median ratio min-norm / MAP | < F/4 pinv / min-norm / MAP | converged |"
          " MAP iterations median (max) | min-norm cones active |")  # fmt: skip
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    print("\n".join(rows))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(14, 3.4), sharey=True)
    bins = np.linspace(0, args.F, 61)
    for ax, K in zip(axes, (2, 3, 4, 6), strict=True):
        r = results[K]
        ax.hist(r["pinv"].ravel(), bins=bins, density=True, alpha=0.55, label="pinv (paper)")
        ax.hist(r["cone_min_norm"].ravel(), bins=bins, density=True, alpha=0.45,
                label="cones, min-norm")  # fmt: skip
        ax.hist(r["cone"].ravel(), bins=bins, density=True, alpha=0.45, label="cones, MAP")
        for key, color in (("pinv", "C0"), ("cone_min_norm", "C1"), ("cone", "C2")):
            sigma = math.sqrt(float(np.mean(r[key] ** 2)))
            x = np.linspace(0, args.F, 200)
            ax.plot(x, np.sqrt(2 / np.pi) / sigma * np.exp(-(x**2) / (2 * sigma**2)), color=color,
                    lw=1, label=f"half-Gauss sigma={sigma / args.F:.2f} F")  # fmt: skip
        ax.set_title(f"K = {K} pushing forces")
        ax.set_xlabel("per-force error norm (N)")
        ax.legend(fontsize=7)
    axes[0].set_ylabel("density")
    fig.suptitle(f"iCub forearm and hand, |f| ~ U[0, {args.F:g}] N inside {HALF_ANGLE} rad cones",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"histogram: {Path(args.out).resolve()}")


if __name__ == "__main__":
    main()
